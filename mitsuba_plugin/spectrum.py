"""RGB colors of a solid texture as the spectra of the current Mitsuba variant.

An RGB variant takes a color as it is and a monochrome one its luminance. A spectral
variant upsamples it as Mitsuba's own ``srgb`` reflectance does: the sigmoid of a
quadratic in the wavelength (Jakob & Hanika 2019), whose three coefficients Mitsuba reads
from its table ``data/srgb.coeff``. Mitsuba looks coefficients up one scalar color at a
time; :func:`srgb_coefficients` is the same lookup on Dr.Jit arrays, so it also runs inside
traced renders and on whole wavefronts. :func:`check_upsampling` compares the two on
probe colors before a texture is used, since another Mitsuba release may look up
otherwise: a texture is then refused rather than shown in colors Mitsuba would not give.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

_TABLE = "data/srgb.coeff"
# The coefficient Mitsuba gives black and white grays: the sigmoid is then 0 or 1 at
# every wavelength, to float precision.
_GRAY_LIMIT = 8192.0


# Mitsuba's luminance weights (linear sRGB), as the float32 constants it multiplies by.
_LUMINANCE = tuple(float(np.float32(w)) for w in (0.212671, 0.715160, 0.072169))


def spectrum(rgb: mi.Color3f, wavelengths: mi.UnpolarizedSpectrum) -> mi.UnpolarizedSpectrum:
    """``rgb`` as the current variant's spectrum at ``wavelengths`` (an interaction's; read
    in spectral variants only)."""
    if mi.is_spectral:
        return mi.srgb_model_eval(srgb_coefficients(rgb), wavelengths)
    if mi.is_monochromatic:
        return mi.UnpolarizedSpectrum(luminance(rgb))
    return rgb


def extinction_spectrum(rgb: mi.Color3f,
                        wavelengths: mi.UnpolarizedSpectrum) -> mi.UnpolarizedSpectrum:
    """Extinctions ``rgb`` (not negative, unbounded) as the current variant's spectrum, as
    Mitsuba's ``gridvolume`` upsamples three channels: in a spectral variant, the
    reflectance model of ``rgb / s`` times ``s``, twice the largest channel, so that values
    above 1 are kept rather than clipped; as :func:`spectrum` in the others."""
    if not mi.is_spectral:
        return spectrum(rgb, wavelengths)
    scale = 2.0 * dr.maximum(dr.maximum(rgb[0], rgb[1]), rgb[2])
    unit = mi.Color3f(rgb) / dr.maximum(1e-8, scale)
    return scale * mi.srgb_model_eval(srgb_coefficients(unit), wavelengths)


def luminance(rgb: mi.Color3f) -> mi.Float:
    """``mi.luminance`` of ``rgb`` in float64 in one order of operations, rounded to float32
    once: Mitsuba's scalar and LLVM builds compile theirs differently, a float32 ulp apart
    on some colors, and a point's value must not depend on the variant."""
    if not dr.is_jit_v(mi.Float):
        # mi.Float is Python's float here: rounded as the JIT variants' float32 is.
        return float(np.float32(sum(w * float(c) for w, c in zip(_LUMINANCE, rgb, strict=True))))
    wide = dr.float64_array_t(mi.Float)
    r, g, b = (wide(c) for c in rgb)
    return mi.Float(_LUMINANCE[0] * r + _LUMINANCE[1] * g + _LUMINANCE[2] * b)


def srgb_coefficients(rgb: mi.Color3f) -> mi.Vector3f:
    """Coefficients of the spectral upsampling model for colors ``rgb``, clamped to
    [0, 1] first: ``mi.srgb_model_fetch``, for JIT arrays too."""
    if not dr.is_jit_v(mi.Float):
        return mi.srgb_model_fetch(mi.ScalarColor3f(rgb))
    res, scale, data = _table_arrays(mi.variant())
    c = [dr.clip(v, 0.0, 1.0) for v in rgb]
    # The table is indexed by the largest component (the last of equal ones) and the
    # other two relative to it, in cyclic order.
    largest, z = mi.UInt32(0), c[0]
    for j in (1, 2):
        take = c[j] >= z
        largest = dr.select(take, j, largest)
        z = dr.select(take, c[j], z)
    after = dr.select(largest == 0, c[1], dr.select(largest == 1, c[2], c[0]))
    before = dr.select(largest == 0, c[2], dr.select(largest == 1, c[0], c[1]))
    step = (res - 1) / dr.select(z > 0.0, z, 1.0)  # black is a gray: its value comes below
    x, y = after * step, before * step
    xi = dr.minimum(mi.UInt32(x), res - 2)
    yi = dr.minimum(mi.UInt32(y), res - 2)
    # The interval of the table's (uneven) brightness steps that holds z.
    zi = dr.binary_search(1, res - 1, lambda i: dr.gather(mi.Float, scale, i) <= z) - 1
    z0_at = dr.gather(mi.Float, scale, zi)
    z1 = (z - z0_at) / (dr.gather(mi.Float, scale, zi + 1) - z0_at)
    x1, y1 = x - mi.Float(xi), y - mi.Float(yi)
    x0, y0, z0 = 1.0 - x1, 1.0 - y1, 1.0 - z1
    base = (((largest * res + zi) * res + yi) * res + xi) * 3
    dx, dy, dz = 3, 3 * res, 3 * res * res

    def at(offset: Any) -> mi.Float:
        return dr.gather(mi.Float, data, offset)

    out = []
    for j in range(3):
        o = base + j
        near = (at(o) * x0 + at(o + dx) * x1) * y0 + (at(o + dy) * x0 + at(o + dy + dx) * x1) * y1
        o = o + dz
        far = (at(o) * x0 + at(o + dx) * x1) * y0 + (at(o + dy) * x0 + at(o + dy + dx) * x1) * y1
        out.append(near * z0 + far * z1)
    # Grays are Mitsuba's special case: a flat spectrum, the sigmoid's inverse at the gray.
    gray = (c[0] == c[1]) & (c[1] == c[2])
    v = c[0]
    flat = dr.select(v <= 0.0, -_GRAY_LIMIT,
                     dr.select(v >= 1.0, _GRAY_LIMIT, (v - 0.5) / dr.sqrt(v * (1.0 - v))))
    return mi.Vector3f(dr.select(gray, 0.0, out[0]), dr.select(gray, 0.0, out[1]),
                       dr.select(gray, flat, out[2]))


def check_upsampling() -> None:
    """Refuse, with a RuntimeError, a spectral variant whose Mitsuba upsamples probe
    colors otherwise than :func:`srgb_coefficients`; nothing to check in other variants
    and in scalar ones, which call Mitsuba's own lookup."""
    if mi.is_spectral and dr.is_jit_v(mi.Float):
        _check_upsampling(mi.variant())


def _probe_colors() -> np.ndarray:
    """Grays from black to white, primaries, colors beyond [0, 1] and random ones."""
    gray = np.linspace(0.0, 1.0, 9)[:, None].repeat(3, axis=1)
    edges = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, 1, 1], [1, 0, 1],
                      [-0.5, 0.3, 2.0], [0.2, 0.2, 0.7], [0.7, 0.2, 0.2], [0.4, 0.7, 0.4]])
    random = np.random.default_rng(0).uniform(0.0, 1.0, (45, 3))
    return np.concatenate([gray, edges, random]).astype(np.float32)


@cache
def _check_upsampling(variant: str) -> None:
    probes = _probe_colors()
    ours = np.array(srgb_coefficients(mi.Color3f(probes.T))).T
    theirs = np.array([list(mi.srgb_model_fetch(mi.ScalarColor3f(*c))) for c in probes])
    # Equal to the bit on the CPU (tests); CUDA divides in approximate float32, so there
    # the lookup may differ in the last bits, which the tolerance allows.
    if not np.allclose(ours, theirs, rtol=1e-4, atol=1e-6):
        worst = int(np.argmax(np.abs(ours - theirs).max(axis=1)))
        raise RuntimeError(
            f"warptex: Mitsuba {mi.__version__} ({variant}) upsamples RGB to spectra "
            f"otherwise than warptex: for color {probes[worst].tolist()} Mitsuba gives "
            f"coefficients {theirs[worst].tolist()}, warptex {ours[worst].tolist()}; render "
            "lazy_solid textures in an RGB or monochrome variant")


@cache
def _table_arrays(variant: str) -> tuple[int, mi.Float, mi.Float]:
    """The coefficient table as the arrays of ``variant``: resolution, brightness steps,
    and (3, res, res, res, 3) coefficients, flat."""
    res, scale, data = _table(str(mi.file_resolver().resolve(_TABLE)))
    return res, mi.Float(scale), mi.Float(data)


@cache
def _table(path: str) -> tuple[int, np.ndarray, np.ndarray]:
    """Mitsuba's upsampling table at ``path``: a ``SPEC`` header, the resolution, the
    brightness steps and the coefficients, as float32."""
    try:
        raw = Path(path).read_bytes()
    except OSError as e:
        raise RuntimeError(f"{path}: cannot read Mitsuba's spectral upsampling table "
                           f"({e.strerror or e})") from None
    res = int(np.frombuffer(raw, np.uint32, 1, 4)[0]) if len(raw) >= 8 else 0
    size = 8 + 4 * (res + 9 * res**3)
    if raw[:4] != b"SPEC" or res < 2 or len(raw) < size:  # as Mitsuba, ignore what follows
        raise RuntimeError(f"{path}: not Mitsuba's spectral upsampling table")
    scale = np.frombuffer(raw, np.float32, res, 8)
    return res, scale, np.frombuffer(raw, np.float32, 9 * res**3, 8 + 4 * res)
