"""sRGB encoding of colors (IEC 61966-2-1): what a renderer makes of an 8-bit photo's
colors, and back. An exemplar keeps its colors as stored (``Exemplar.srgb`` says how they
are encoded); a voxel averages three of them; renderers and file formats that take linear
colors get them decoded here, in float64 rounded once to float32, so that every decoder of
the project (NumPy, Dr.Jit, a Python float) gives the same bits.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from warptex.settings import check_flag


def srgb_to_linear(values: Any) -> np.ndarray:
    """Linear float32 values of sRGB-encoded float32 ``values`` in [0, 1] (IEC 61966-2-1),
    what a renderer makes of the colors of an exemplar whose ``srgb`` is set; the plugin's
    lookups decode alike (:func:`srgb_decoded`), to the same bits."""
    wide = _float_values(values).astype(np.float32).astype(np.float64)
    with np.errstate(invalid="ignore"):  # the power of a negative value, not selected
        return srgb_decoded(wide, np.where).astype(np.float32)


def _float_values(values: Any) -> np.ndarray:
    """``values`` as an array of floats, a TypeError otherwise: 8-bit colors (0 to 255)
    taken for values in [0, 1] came out 10^5 times too bright."""
    array = np.asarray(values)
    if not np.issubdtype(array.dtype, np.floating):
        raise TypeError(f"colors must be floats in [0, 1] (8-bit ones divided by 255), got "
                        f"{array.dtype}")
    return array


def srgb_decoded(values: Any, select: Callable) -> Any:
    """The formula of :func:`srgb_to_linear` on float64 ``values``: NumPy arrays with
    ``np.where``, Dr.Jit arrays with ``drjit.select``, a Python float with a plain choice
    (``select(low, a, b)`` is ``a if low else b``). Each decoder of float32 colors widens them
    to float64, decodes here and rounds the result to float32 once: float32 powers differ
    between NumPy, Dr.Jit and the C library in their last bits, float64 ones rounded to
    float32 agree but within float64 error of a rounding boundary (one value in ~10^7)."""
    return select(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(values: np.ndarray) -> np.ndarray:
    """sRGB-encoded float32 values of linear ``values``, clipped to [0, 1] first: what an
    8-bit image shows of a linear exemplar's colors (the inverse of :func:`srgb_to_linear`),
    computed in float64 like it."""
    values = np.clip(_float_values(values).astype(np.float32), 0, 1).astype(np.float64)
    return np.where(values <= 0.0031308, values * 12.92,
                    1.055 * values ** (1 / 2.4) - 0.055).astype(np.float32)


_REENCODED_ROWS = 1 << 18


def color_channels(channels: int, alpha: bool = False) -> int:
    """How many of an image's ``channels`` are colors, the leading ones: three (RGB) where
    at least three come before a kept ``alpha`` (the last channel), else one (gray). Those
    between are data, as the exemplars' files name them (README, Exemplars)."""
    return 3 if channels - (alpha and channels > 1) >= 3 else 1


def reencoded(values: np.ndarray, *, srgb: bool, to_srgb: bool,
              alpha: bool = False) -> np.ndarray:
    """``values`` (..., C), whose colors are sRGB-encoded if ``srgb``, as float32 with the
    colors sRGB-encoded if ``to_srgb``, else linear: what a file format's readers assume.
    Colors are the leading channels (:func:`color_channels`; ``alpha``: the last channel is
    a kept alpha); data and alpha are kept as they are."""
    out = np.array(_float_values(values), np.float32, order="C")
    if out.ndim == 0:
        raise ValueError("values must be an array of colors, channels last (..., C), got one "
                         "number")
    if check_flag("srgb", srgb) != check_flag("to_srgb", to_srgb):
        color = color_channels(out.shape[-1], check_flag("alpha", alpha))
        convert = linear_to_srgb if to_srgb else srgb_to_linear
        rows = out.reshape(-1, out.shape[-1])  # a view of ``out``
        # In parts: the float64 the conversion works in would take several volumes' memory.
        for start in range(0, len(rows), _REENCODED_ROWS):
            part = rows[start : start + _REENCODED_ROWS, :color]
            part[...] = convert(part)
    return out
