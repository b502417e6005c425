"""Labelled picture sheets: exemplars beside slices of solid textures (Dong 2008, Fig. 8)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from warptex.metrics import axis_slices

_LABEL_HEIGHT = 14
_GAP = 4


def to_rgb8(image: np.ndarray) -> np.ndarray:
    """An (H, W, C) float image in [0, 1] as 8-bit RGB (gray repeated, extra channels dropped)."""
    img = np.clip(np.asarray(image, np.float32), 0.0, 1.0)
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    return (img[:, :, :3] * 255.0 + 0.5).astype(np.uint8)


def volume_row(volume: np.ndarray, depth: int | None = None) -> list[tuple[str, np.ndarray]]:
    """The three axis-aligned slices through ``volume`` (middle by default), labelled."""
    out = []
    for axis, name in enumerate("xyz"):
        d = volume.shape[axis] // 2 if depth is None else depth
        sub = np.take(volume, [d], axis=axis)
        out.append((f"{name} = {d}", axis_slices(sub, axis, 1)[0]))
    return out


def sheet(rows: list[tuple[str, list[tuple[str, np.ndarray]]]], scale: int = 2) -> np.ndarray:
    """Compose labelled rows of labelled images into one 8-bit RGB sheet."""
    tiles = [[(label, to_rgb8(img)) for label, img in images] for _, images in rows]
    cell_h = max(t.shape[0] for row in tiles for _, t in row) * scale
    cell_w = max(t.shape[1] for row in tiles for _, t in row) * scale
    row_label_w = 8 * max(len(name) for name, _ in rows) + _GAP
    ncols = max(len(row) for row in tiles)
    height = len(rows) * (cell_h + _LABEL_HEIGHT + _GAP) + _GAP
    width = row_label_w + ncols * (cell_w + _GAP) + _GAP
    canvas = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for r, ((name, _), row) in enumerate(zip(rows, tiles, strict=True)):
        y = _GAP + r * (cell_h + _LABEL_HEIGHT + _GAP)
        draw.text((_GAP, y + _LABEL_HEIGHT + cell_h // 2 - 6), name, fill=(0, 0, 0))
        for c, (label, tile) in enumerate(row):
            x = row_label_w + c * (cell_w + _GAP)
            draw.text((x, y), label, fill=(0, 0, 0))
            img = Image.fromarray(tile).resize(
                (tile.shape[1] * scale, tile.shape[0] * scale), Image.NEAREST
            )
            canvas.paste(img, (x, y + _LABEL_HEIGHT))
    return np.asarray(canvas)


def save_png(image: np.ndarray, path: str | Path) -> None:
    """Write an 8-bit image atomically (temporary name, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    Image.fromarray(image).save(tmp, format="PNG")
    os.replace(tmp, path)
