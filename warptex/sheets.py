"""Labelled picture sheets: exemplars beside slices of solid textures (Dong 2008, Fig. 8)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from warptex.archive import write_atomically
from warptex.metrics import axis_slices

_LABEL_HEIGHT = 14
_GAP = 4


def to_rgb(image: np.ndarray) -> np.ndarray:
    """An (H, W, C) float image as float32 RGB clipped to [0, 1]: gray (with or without
    alpha) repeated, channels past RGB dropped."""
    img = np.clip(np.asarray(image, np.float32), 0.0, 1.0)
    if img.shape[2] < 3:
        img = np.repeat(img[:, :, :1], 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3])


def to_rgb8(image: np.ndarray) -> np.ndarray:
    """An (H, W, C) float image in [0, 1] as 8-bit RGB, as :func:`to_rgb` makes it RGB."""
    return (to_rgb(image) * 255.0 + 0.5).astype(np.uint8)


def to_png8(image: np.ndarray, alpha: bool) -> np.ndarray:
    """An (H, W, C) float image in [0, 1] as an 8-bit PNG keeps it: its colors as
    :func:`to_rgb8` makes them RGB, then, with ``alpha``, its last channel as the PNG's
    alpha, as stored (alpha is no color: never sRGB-encoded)."""
    if not alpha:
        return to_rgb8(image)
    opacity = (np.clip(image[:, :, -1], 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return np.dstack([to_rgb8(image[:, :, :-1]), opacity])


def volume_row(volume: np.ndarray, depth: int | None = None) -> list[tuple[str, np.ndarray]]:
    """The three axis-aligned slices through ``volume`` (middle by default), labelled."""
    out = []
    for axis, name in enumerate("xyz"):
        d = volume.shape[axis] // 2 if depth is None else depth
        sub = np.take(volume, [d], axis=axis)
        out.append((f"{name} = {d}", axis_slices(sub, axis, 1)[0]))
    return out


def sheet(rows: list[tuple[str, list[tuple[str, np.ndarray]]]], cell: int = 160,
          title: str | None = None) -> np.ndarray:
    """Compose labelled rows of labelled images into one 8-bit RGB sheet, under a ``title``
    line if given; every image is scaled to fit a ``cell`` x ``cell`` square (pixels stay
    sharp when enlarged)."""
    row_label_w = 8 * max(len(name) for name, _ in rows) + _GAP
    ncols = max(len(images) for _, images in rows)
    top = 0 if title is None else _LABEL_HEIGHT + _GAP
    height = top + len(rows) * (cell + _LABEL_HEIGHT + _GAP) + _GAP
    width = max(row_label_w + ncols * (cell + _GAP), 7 * len(title or "") + _GAP) + _GAP
    canvas = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    if title is not None:
        draw.text((_GAP, _GAP), title, fill=(0, 0, 0))
    for r, (name, images) in enumerate(rows):
        y = top + _GAP + r * (cell + _LABEL_HEIGHT + _GAP)
        draw.text((_GAP, y + _LABEL_HEIGHT + cell // 2 - 6), name, fill=(0, 0, 0))
        for c, (label, image) in enumerate(images):
            x = row_label_w + c * (cell + _GAP)
            draw.text((x, y), label, fill=(0, 0, 0))
            tile = Image.fromarray(to_rgb8(image))
            scale = cell / max(tile.size)
            size = (max(1, round(tile.size[0] * scale)), max(1, round(tile.size[1] * scale)))
            resample = Image.NEAREST if scale >= 1 else Image.LANCZOS
            canvas.paste(tile.resize(size, resample), (x, y + _LABEL_HEIGHT))
    return np.asarray(canvas)


def save_png(image: np.ndarray, path: str | Path) -> None:
    """Write an 8-bit image atomically (temporary name, then rename)."""
    write_atomically(path, png_writer(image))


def png_writer(image: np.ndarray) -> Callable[[Path], None]:
    """What writes an 8-bit image as PNG to the file it is given (``write_atomically``'s
    ``write``)."""
    return lambda path: Image.fromarray(image).save(path, format="PNG")
