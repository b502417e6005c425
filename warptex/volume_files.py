"""Volumes and images written for other tools: NumPy, OpenEXR and Mitsuba 3 grid volumes.

Every writer goes through :func:`warptex.archive.write_atomically`, so a file is either
whole or absent, never half-written. OpenEXR files and Mitsuba grids hold linear colors, as
the tools reading them assume: the sRGB-encoded colors of 8- and 16-bit exemplars are decoded
there (``srgb=True``), while ``.npy`` files keep every value as synthesized.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np

from warptex.archive import endings, write_atomically
from warptex.settings import check_file_name, check_flag, names_folder
from warptex.srgb import color_channels, reencoded


def write_volume(path: str | Path, volume: np.ndarray, *, srgb: bool,
                 alpha: bool = False) -> None:
    """Write an (X, Y, Z, C) float volume by the file's suffix: ``.npy`` as it is, ``.exr``
    as its z-slices side by side (:func:`exr_sheet`), ``.vol`` as a Mitsuba 3 grid volume
    over the unit box (Mitsuba maps it to [0, 1]^3: a scene places and scales it with the
    volume's ``to_world``, so voxels of a box whose sides differ come out stretched unless
    the scene scales by the sides). ``srgb``: whether the colors are sRGB-encoded, as those
    of an exemplar whose ``Exemplar.srgb`` is set: ``.exr`` and ``.vol`` get them decoded.
    ``alpha``: whether the last channel is an alpha (``Exemplar.kept_alpha``), which
    ``.exr`` names A; other channels past the colors are data, named by number. Besides
    ``volume`` the write holds up to :data:`WRITE_COPIES` copies of it, by format.
    Raises ValueError for another suffix or a folder's name, and OSError when the file
    cannot be written."""
    _write(path, _float_array(volume, 4, "volume", "(X, Y, Z, C)"), check_flag("srgb", srgb),
           check_flag("alpha", alpha), "a volume file", _VOLUME_WRITERS)


def write_image(path: str | Path, image: np.ndarray, *, srgb: bool,
                alpha: bool = False) -> None:
    """Write an (H, W, C) float image without loss: ``.npy`` or single-part OpenEXR, which
    gets sRGB-encoded colors decoded (``srgb`` and ``alpha`` as for :func:`write_volume`)."""
    _write(path, _float_array(image, 3, "image", "(H, W, C)"), check_flag("srgb", srgb),
           check_flag("alpha", alpha), "a lossless image file", _IMAGE_WRITERS)


def _write(path: str | Path, data: np.ndarray, srgb: bool, alpha: bool, kind: str,
           writers: dict[str, Callable[[Path, np.ndarray, bool], None]]) -> None:
    """``data`` written atomically by the writer of ``path``'s suffix; every format but
    ``.npy`` holds linear colors, so sRGB-encoded ones (``srgb``) are decoded for it."""
    given = path
    path = check_file_name("path", path)
    if isinstance(given, str) and names_folder(given):
        raise ValueError(f"{given}: names a folder, not a file")
    writer = writers.get(path.suffix.lower())
    if writer is None:
        raise ValueError(f"{path}: {kind} must end in {endings(list(writers))}")
    if writer is not _write_npy:
        data = reencoded(data, srgb=srgb, to_srgb=False, alpha=alpha)
    write_atomically(path, lambda tmp: writer(tmp, data, alpha))


def exr_sheet(volume: np.ndarray) -> np.ndarray:
    """The z-slices of an (X, Y, Z, C) volume side by side: pixel (row y, column z*X + x)
    holds voxel (x, y, z), so the sheet is Y rows by Z*X columns."""
    x, y, z, c = volume.shape
    return volume.transpose(1, 2, 0, 3).reshape(y, z * x, c)


def _float_array(data, ndim: int, name: str, layout: str) -> np.ndarray:
    """``data`` as a float array of ``ndim`` axes, or a clear error: the formats hold float
    colors, and an integer array would be written as 0-255 floats."""
    array = np.asarray(data)
    if array.ndim != ndim:
        raise ValueError(f"the {name} must be a {layout} array, got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.floating):
        raise TypeError(f"the {name} must hold float colors, got {array.dtype}")
    if 0 in array.shape:
        raise ValueError(f"the {name} is empty: shape {array.shape}")
    return array


def _write_npy(path: Path, array: np.ndarray, alpha: bool = False) -> None:
    """NumPy's ``.npy`` format, its data written by Python: NumPy's own writer says only
    that a write fell short ("98304 requested and 6112 written"), Python why (a full disk)."""
    array = np.ascontiguousarray(array)
    with open(path, "wb") as file:
        np.lib.format.write_array_header_1_0(file, np.lib.format.header_data_from_array_1_0(array))
        file.write(memoryview(array).cast("B"))


def _exr_channel_names(channels: int, alpha: bool) -> list[str]:
    """Named as the exemplars' channels are read, so that OpenEXR's and Mitsuba's readers
    know them: colors (three of RGB and more, one of gray) R, G, B or Y, an ``alpha`` last
    A, data channels between by number (C1, C3, ...)."""
    alpha = alpha and channels > 1  # a kept alpha alone is read as one color channel
    color = list("RGB") if color_channels(channels, alpha) == 3 else ["Y"]
    data = [f"C{c}" for c in range(len(color), channels - alpha)]
    return color + data + ["A"] * alpha


def _write_exr_volume(path: Path, volume: np.ndarray, alpha: bool) -> None:
    x, y, z, channels = volume.shape
    layout = f"z-slices side by side, {x}x{y}x{z} voxels (x, y, z)"
    # A sheet per channel: one copy of the volume in all, not the whole sheet then its planes.
    planes = [exr_sheet(volume[..., c : c + 1])[..., 0] for c in range(channels)]
    _write_exr_planes(path, planes, alpha, {"warptexLayout": layout})


def _write_exr(path: Path, image: np.ndarray, alpha: bool) -> None:
    _write_exr_planes(path, [image[..., c] for c in range(image.shape[2])], alpha)


def _write_exr_planes(path: Path, planes: list[np.ndarray], alpha: bool,
                      extra: dict | None = None) -> None:
    """An image's (H, W) channel ``planes`` as a single-part scanline OpenEXR file, float32."""
    import OpenEXR

    names = _exr_channel_names(len(planes), alpha)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(extra or {})
    pixels = {name: np.ascontiguousarray(plane, np.float32)
              for name, plane in zip(names, planes, strict=True)}
    # Through a Python file: OpenEXR takes no name that is not UTF-8 (an old share's).
    with OpenEXR.File(header, pixels) as file, open(path, "wb") as stream:
        file.write(stream)


def _write_vol(path: Path, volume: np.ndarray, alpha: bool = False) -> None:
    """Mitsuba 3 grid volume: b'VOL', version 3, float32 encoding, x fastest, the unit box
    as its bounds."""
    x, y, z, c = volume.shape
    header = b"VOL" + struct.pack("<B4i", 3, 1, x, y, z) + struct.pack("<i6f", c, 0, 0, 0, 1, 1, 1)
    # Data index ((z * Y + y) * X + x) * C + c: each z-slice transposed to (y, x, c), one at
    # a time, so the write holds one slice's copy, not the volume's.
    with open(path, "wb") as file:
        file.write(header)
        for k in range(z):
            file.write(np.ascontiguousarray(volume[:, :, k].transpose(1, 0, 2), dtype="<f4"))


_VOLUME_WRITERS = {".npy": _write_npy, ".exr": _write_exr_volume, ".vol": _write_vol}
# Copies of a volume that its write holds besides it, rounded up from what
# benchmarks/bench_write_memory.py measures (sRGB-decoded at 256^3: .npy 0, .vol 1.13,
# .exr 2.27; more at smaller sizes, where fixed buffers weigh more: 2.04 and 2.57 at 128^3,
# a MiB past .vol's 2 there, which no memory check of so small a volume turns on).
WRITE_COPIES = {".npy": 0, ".exr": 3, ".vol": 2}
_IMAGE_WRITERS = {".npy": _write_npy, ".exr": _write_exr}
VOLUME_FORMATS = tuple(_VOLUME_WRITERS)
