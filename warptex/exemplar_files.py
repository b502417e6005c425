"""Exemplar image files read as stored: PNG (pypng where Pillow would change the values),
OpenEXR (colors, other channels and alpha by name), NumPy ``.npy`` and what else Pillow reads,
with whether they hold an alpha channel and sRGB-encoded colors.

Values keep their stored dtype here; :mod:`warptex.exemplar` scales and checks them.
"""

from __future__ import annotations

import io
import re
import struct
import tokenize
import zlib
from pathlib import Path

import numpy as np
import png
from PIL import Image, ImageOps, UnidentifiedImageError

from warptex.archive import input_file_problem
from warptex.thread_warnings import library_warnings, warn

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_EXR_MAGIC = b"\x76\x2f\x31\x01"
_NPY_MAGIC = b"\x93NUMPY"


class ExemplarError(ValueError):
    """An exemplar could not be used; the message names the file (or ``array``) and the problem."""


def stored_srgb(array: object) -> bool:
    """Whether ``array`` holds 8- or 16-bit integers, which images store sRGB-encoded."""
    return native_order(np.asarray(array).dtype) in (np.uint8, np.uint16)


def native_order(dtype: np.dtype) -> np.dtype:
    """``dtype`` in this machine's byte order: a big-endian uint16 (``>u2``, as a .npy
    written on another machine or a PNG's raw rows hold) is no uint16 to ``==``."""
    return dtype.newbyteorder("=")


def read_image(path: Path) -> tuple[np.ndarray, bool, bool]:
    """Read an image file as ``(H, W[, C])`` in its stored dtype, whether it has alpha and
    whether its colors are sRGB-encoded."""
    problem = input_file_problem(path, "image file")
    if problem is not None:
        raise ExemplarError(f"{path}: {problem}")
    try:
        with path.open("rb") as file:
            head = file.read(8)
    except OSError as error:
        raise ExemplarError(f"{path}: cannot read file ({error.strerror})") from None
    if head.startswith(_PNG_MAGIC):
        return *_read_png(path), True
    if head.startswith(_EXR_MAGIC):
        return *_read_exr(path), False
    if head.startswith(_NPY_MAGIC):
        pixels = _read_npy(path)
        return pixels, False, stored_srgb(pixels)
    pixels, has_alpha = _read_pillow(path, head)
    return pixels, has_alpha, stored_srgb(pixels)


def _read_png(path: Path) -> tuple[np.ndarray, bool]:
    # pypng where Pillow differs: Pillow reduces 16-bit RGB(A) PNGs to 8 bits, scales 1- to
    # 4-bit grey to 8 bits, and gives an RGB or grey image's transparent color (tRNS) no
    # alpha channel. Elsewhere Pillow, which decodes in C: pypng takes about a second a
    # megapixel, a photo's quarter of a minute before it is shrunk.
    try:
        with path.open("rb") as file:
            reader = png.Reader(file=file)
            reader.preamble()
    except (png.Error, OSError, ValueError, zlib.error) as error:
        raise ExemplarError(f"{path}: unreadable PNG ({error})") from None
    if reader.bitdepth == 8 and (reader.colormap or reader.trns is None):
        try:  # not turned by an EXIF orientation, as pypng's are not
            return _pillow_decoded(path, upright=False)
        except (OSError, ValueError, SyntaxError, Image.DecompressionBombError):
            pass  # what Pillow refuses (over its pixel limit, a large text chunk) pypng reads
    chunks = _png_chunks_before_pixels(path)
    _warn_of_color_profile(_png_color_profile(chunks.get(b"iCCP")), path)
    frames = int.from_bytes(chunks.get(b"acTL", b"")[:4], "big")  # an APNG's frame count
    if frames > 1:
        warn(f"{path}: an animation of {frames} frames, of which the first is read",
             stacklevel=4)
    return _read_png_with_pypng(path)


def _png_chunks_before_pixels(path: Path) -> dict[bytes, bytes]:
    """The chunks of a PNG that come before its pixels (IDAT), by kind, the first of each:
    where a color profile (iCCP) and an animation's frame count (acTL) are, which pypng
    gives as chunks but does not decode; none where the chunks cannot be read (pypng's
    decoding then says why)."""
    found: dict[bytes, bytes] = {}
    try:
        with open(path, "rb") as file:
            for kind, data in png.Reader(file=file).chunks():
                if kind == b"IDAT":
                    break
                found.setdefault(kind, data)
    except (png.Error, OSError, ValueError, zlib.error):
        pass
    return found


def _png_color_profile(chunk: bytes | None) -> bytes | None:
    """The ICC profile of a PNG's iCCP ``chunk`` (a name, a compression method byte, then
    the profile, zlib-compressed); None without one or where it cannot be decompressed."""
    if chunk is None:
        return None
    try:
        return zlib.decompress(chunk.partition(b"\0")[2][1:])
    except zlib.error:
        return None


def _read_png_with_pypng(path: Path) -> tuple[np.ndarray, bool]:
    try:
        with path.open("rb") as file:
            reader = png.Reader(file=file)
            reader.preamble()
            # The stored values, as Mitsuba and Pillow read them: pypng would rescale them
            # to the significant bits of an sBIT chunk (RGB565 to 6 bits a channel).
            reader.sbit = None
            width, height, rows, info = reader.asDirect()
            pixels = np.vstack([np.asarray(row) for row in rows])
    except (png.Error, OSError, ValueError, zlib.error) as error:
        raise ExemplarError(f"{path}: unreadable PNG ({error})") from None
    planes = info["planes"]
    pixels = pixels.reshape(height, width, planes)
    bitdepth = info["bitdepth"]
    if bitdepth == 16:
        pixels = pixels.astype(np.uint16)
    elif bitdepth == 8:
        pixels = pixels.astype(np.uint8)
    else:  # 1, 2 or 4 bits: rescale so that full intensity is 1.0 like any other depth
        pixels = pixels.astype(np.float32) / np.float32(2**bitdepth - 1)
    return pixels, bool(info["alpha"])


def _read_exr(path: Path) -> tuple[np.ndarray, bool]:
    import OpenEXR

    try:
        # Through a Python file: OpenEXR takes no name that is not UTF-8 (an old share's).
        with open(path, "rb") as stream, OpenEXR.File(stream, separate_channels=True) as file:
            channels = _exr_part_channels(file.parts, path)
    except ExemplarError:  # a ValueError, but said of the file already
        raise
    except (RuntimeError, OSError, ValueError) as error:
        raise _exr_levels_refused(path) or ExemplarError(
            f"{path}: unreadable OpenEXR file ({error})") from None
    if not channels:  # OpenEXR reads no part of a file cut short, saying so on stderr
        raise _exr_levels_refused(path) or ExemplarError(
            f"{path}: damaged or truncated OpenEXR file (no part readable)")
    order, alpha = _exr_channel_order(list(channels), path)
    for name in order:
        if np.issubdtype(channels[name].dtype, np.integer):
            raise ExemplarError(f"{path}: OpenEXR channel {name} holds integers (object or "
                                "material ids), not colors")
        # An alpha is checked where it is kept (alpha="keep"), not where it is dropped.
        if not (alpha and name == order[-1]) and not np.isfinite(channels[name]).all():
            raise ExemplarError(f"{path}: image contains NaN or Inf values (in OpenEXR "
                                f"channel {name})")
    try:
        pixels = np.stack([channels[name].astype(np.float32) for name in order], axis=2)
    except ValueError:
        raise ExemplarError(f"{path}: OpenEXR channels have different sizes") from None
    return pixels, alpha


def _exr_levels_refused(path: Path) -> ExemplarError | None:
    """The error of a mip- or rip-mapped tiled OpenEXR file, whose levels OpenEXR's Python
    module cannot read (it reads no part of one, as of a damaged file); None for others."""
    import OpenEXR

    try:
        with open(path, "rb") as stream, OpenEXR.File(stream, header_only=True) as file:
            tiles = file.header().get("tiles")
    except (RuntimeError, OSError, ValueError):
        return None
    if tiles is None or tiles.mode == OpenEXR.ONE_LEVEL:
        return None
    kind = "mip" if tiles.mode == OpenEXR.MIPMAP_LEVELS else "rip"
    return ExemplarError(f"{path}: a {kind}-mapped tiled OpenEXR file, whose levels OpenEXR's "
                         f"Python module cannot read: save it without {kind}-maps (as scan "
                         "lines or one level of tiles)")


def _exr_part_channels(parts: list, path: Path) -> dict[str, np.ndarray]:
    """The channels of an OpenEXR file's parts (a renderer's passes) by name, each part
    after the first told apart as a layer (``diffuse.R``), the first as the default layer,
    which viewers show; a part's channels already named after it (Nuke's) keep their names.
    """
    channels: dict[str, np.ndarray] = {}
    for n, part in enumerate(parts):
        for name, channel in part.channels.items():
            layered = n == 0 or name.startswith(f"{part.name()}.")
            full = name if layered else f"{part.name()}.{name}"
            if full in channels:
                raise ExemplarError(f"{path}: OpenEXR channel {full} is in two parts: save "
                                    "the part to use alone")
            channels[full] = channel.pixels
    return channels


def _exr_channel_order(names: list[str], path: Path) -> tuple[list[str], bool]:
    """The channels of an OpenEXR file that make the exemplar, color first in RGB order,
    other channels (depth, roughness, ...) by name, alpha last; and whether there is alpha.

    Channels are told by their name after the layer's prefix (``diffuse.R``), in either
    case, as Mitsuba's bitmap reads them. Of a file with layers, the one layer holding
    colors is read, with a warning naming the channels of the others, left out.
    """
    layers: dict[str, dict[str, str]] = {}
    for name in names:
        layer, _, base = name.rpartition(".")
        same = layers.setdefault(layer, {}).setdefault(base.upper(), name)
        if same != name:
            raise ExemplarError(f"{path}: OpenEXR channels {same} and {name} are one channel "
                                "told apart by case only: save one of them")
    # The layer of RGB colors, else of luminance, the default layer first, as viewers show.
    colored = ([layer for layer, bases in layers.items() if {"R", "G", "B"} & set(bases)]
               or [layer for layer, bases in layers.items() if "Y" in bases])
    if len(colored) > 1 and "" in colored:
        colored = [""]
    if len(colored) > 1:
        raise ExemplarError(f"{path}: OpenEXR file has colors in {len(colored)} layers "
                            f"({', '.join(sorted(colored))}): save the one to use alone")
    if not colored:
        alphas = [n for n in names if n.upper() == "A"]
        rest = sorted((n for n in names if n not in alphas), key=_numbered)
        return rest + alphas, bool(alphas)
    bases = layers[colored[0]]
    color = [bases[c] for c in ("R", "G", "B") if c in bases] or [bases["Y"]]
    alpha = bases.get("A")
    rest = sorted((n for n in bases.values() if n not in color and n != alpha), key=_numbered)
    left_out = sorted(set(names) - set(bases.values()))
    if left_out:
        warn(f"{path}: OpenEXR layer {colored[0] or '(default)'} read, channels of "
             f"other layers left out: {', '.join(left_out)}", stacklevel=5)
    return color + rest + ([alpha] if alpha else []), alpha is not None


def _numbered(name: str) -> list[str | int]:
    """Sort key of channel names with numbers in them taken as numbers: C2 before C10, as
    warptex writes the channels of an image of more than four."""
    return [int(part) if n % 2 else part for n, part in enumerate(re.split(r"(\d+)", name))]


def _read_npy(path: Path) -> np.ndarray:
    try:
        # Mapped first: a header that declares more than the file holds (damaged) is refused
        # before its size is allocated, which may fail or, overcommitted, not.
        return np.array(np.load(path, mmap_mode="r", allow_pickle=False))
    except (OSError, ValueError, SyntaxError, tokenize.TokenError) as error:
        raise ExemplarError(f"{path}: unreadable .npy file ({error})") from None
    except MemoryError as error:
        raise ExemplarError(f"{path}: too large to load ({error})") from None


def _read_pillow(path: Path, head: bytes) -> tuple[np.ndarray, bool]:
    """Pillow's pixels of ``path``, whose first bytes are ``head``; its errors in ours."""
    try:
        return _pillow_decoded(path, upright=True)
    except UnidentifiedImageError:
        if head[:4] in (b"II*\0", b"MM\0*"):  # Pillow reads no float RGB TIFF, among others
            raise ExemplarError(f"{path}: a TIFF file of a kind Pillow cannot read (float "
                                "RGB or 16-bit gray with alpha, say): save it as OpenEXR"
                                ) from None
        raise ExemplarError(f"{path}: not an image (unrecognised file format)") from None
    except Image.DecompressionBombError as error:
        raise ExemplarError(f"{path}: too large to read ({error})") from None
    # Pillow's decoders meet damaged files (a TIFF's page without a size, say) with
    # whichever error their parsing raised.
    except (OSError, ValueError, SyntaxError, TypeError, KeyError, IndexError, EOFError,
            struct.error) as error:
        raise ExemplarError(f"{path}: unreadable image ({str(error) or type(error).__name__})"
                            ) from None


def _pillow_decoded(path: Path, upright: bool) -> tuple[np.ndarray, bool]:
    """Pillow's pixels of ``path``, turned ``upright`` as EXIF says; Pillow's errors, and
    its warnings (corrupt EXIF data) given again naming the file."""
    try:
        # From a file, not a path, which Pillow 13 memory-maps where a TIFF is one
        # uncompressed strip: read at the size its EXIF orientation turns it to, a portrait
        # (orientations 5 to 8) came out scrambled.
        with (library_warnings("PIL") as caught, path.open("rb") as file,
              Image.open(file) as image):
            # Told by the decoder's settings, gone once loaded.
            cut_bits, widened = _bits_cut_to_8(image), _widened_16_bit(image)
            frames = getattr(image, "n_frames", 1)
            image.load()
            # Cameras store portrait photos sideways and say so in EXIF: upright, as
            # viewers show them, since grain and layers run the way the photo shows.
            if upright:
                ImageOps.exif_transpose(image, in_place=True)
            pixels = _pillow_pixels(image, widened)
    except Warning as made_an_error:  # by the process's filters (python -W error)
        raise type(made_an_error)(f"{path}: {made_an_error}") from None
    for warning in caught:
        # What the file holds (corrupt EXIF data), not Pillow's deprecations nor its
        # decompression bomb (a RuntimeWarning): a photograph of 90 to 180 megapixels is the
        # user's own photo, and max_size shrinks it.
        if issubclass(warning.category, UserWarning):
            warn(f"{path}: {warning.message}", warning.category, stacklevel=5)
    if frames > 1:
        warn(f"{path}: an animation of {frames} frames (or pages), of which the first is read",
             stacklevel=5)
    if cut_bits:
        warn(f"{path}: 16-bit color image read as 8 bits (Pillow reads 16-bit RGB and "
             "CMYK TIFF and PPM files so); save it in RGB as a 16-bit PNG or an OpenEXR "
             "file to keep its precision", stacklevel=5)
    _warn_of_color_profile(image.info.get("icc_profile"), path)
    return pixels


# Pillow's decoders of binary and plain-text PNM (PGM, PPM) files, whose levels run to 65535.
_PNM_CODECS = ("ppm", "ppm_plain")
_UNSIGNED_16 = ("I;16", "I;16B", "I;16L", "I;16N")  # raw modes of unsigned 16-bit gray


def _bits_cut_to_8(image: Image.Image) -> bool:
    """Whether Pillow is about to decode 16-bit colors into its 8-bit RGB(A) or CMYK mode:
    a raw mode of 16-bit samples (``RGB;16L``), or a PPM of more than 255 levels."""
    if image.mode not in ("RGB", "RGBA", "CMYK"):
        return False
    for codec, raw, args in _decoders(image):
        if ";16" in raw or (codec in _PNM_CODECS and any(isinstance(a, int) and a > 255
                                                          for a in args)):
            return True
    return False


def _widened_16_bit(image: Image.Image) -> bool:
    """Whether a 32-bit integer (``I``) image is unsigned 16-bit gray that Pillow widened
    (a 16-bit PGM or TIFF), not signed (``I;16S``, ``I;16BS``) or 32-bit samples, which have
    no [0, 1] scale."""
    return all(codec in _PNM_CODECS or raw in _UNSIGNED_16
               for codec, raw, _ in _decoders(image))


def _decoders(image: Image.Image) -> list[tuple[str, str, tuple]]:
    """Each tile's codec, raw mode (the first text of its arguments) and arguments."""
    found = []
    for tile in image.tile:
        args = tile[3] if isinstance(tile[3], tuple) else (tile[3],)
        found.append((tile[0], next((a for a in args if isinstance(a, str)), ""), args))
    return found


def _warn_of_color_profile(profile: bytes | None, path: Path) -> None:
    """Warn that an embedded ICC profile other than sRGB (Adobe RGB, Display P3, a press
    CMYK one) is not applied: its values are taken as sRGB, so colors shift. Converting
    them would make a texture depend on the color management library's version."""
    if not profile:
        return
    try:
        from PIL import ImageCms

        parsed = ImageCms.ImageCmsProfile(io.BytesIO(profile))
        name = ImageCms.getProfileDescription(parsed).strip()
        space = parsed.profile.xcolor_space.strip()
    except (ImportError, OSError, ValueError, TypeError):
        name, space = "", ""
    if space == "GRAY" or "srgb" in name.lower():
        return
    warn(f"{path}: embedded color profile {name or '(unreadable)'!r} not applied: "
         "its values are taken as sRGB, so its colors shift; convert the image to "
         "sRGB first", stacklevel=5)


def _pillow_pixels(image: Image.Image, widened: bool) -> tuple[np.ndarray, bool]:
    mode = image.mode
    if mode.startswith("I;16") and not mode.startswith("I;16S"):
        return np.asarray(image).astype(np.uint16), False
    if mode == "F":
        return np.asarray(image), False
    if mode == "I" and widened:  # Pillow widens 16-bit gray to 32 bits in some formats
        data = np.asarray(image)
        if data.min() >= 0 and data.max() <= 65535:
            return data.astype(np.uint16), False
    if mode.startswith("I"):  # their values, whatever they are, have no [0, 1] scale
        raise ValueError("signed or 32-bit integer pixels are not supported (unsigned 8 or "
                         "16 bits are): save them as float OpenEXR")
    if mode in ("L", "RGB"):
        return np.asarray(image), False
    if mode in ("LA", "RGBA"):
        return np.asarray(image), True
    if mode in ("La", "RGBa"):  # premultiplied alpha (a TIFF's associated one), undone
        return np.asarray(image.convert(mode.upper())), True
    if mode in ("P", "PA"):
        has_alpha = mode == "PA" or "transparency" in image.info
        return np.asarray(image.convert("RGBA" if has_alpha else "RGB")), has_alpha
    if mode == "1":
        return np.asarray(image.convert("L")), False
    return np.asarray(image.convert("RGB")), False
