"""2D exemplars: loading, validation, feature distance and the Gaussian pyramid.

Lazy solid synthesis (Dong et al. 2008, §3) matches neighbourhoods level by level on a Gaussian
pyramid of the exemplar, so an :class:`Exemplar` holds two views of the same pixels: ``colors``,
the channels a texture lookup returns, and ``features``, the channels neighbourhoods are compared
on. ``features`` equals ``colors`` unless a feature-distance channel is added (Lefebvre & Hoppe
2006; Kopf et al. 2007, §6; Dong et al. 2008, §6): a signed distance to the edges of the image's
features that helps matching keep structures such as veins or cells intact. It is appended as
the last feature channel and never returned as color.

Values are float32. 8- and 16-bit images are scaled linearly to [0, 1] (value / 255 or
value / 65535) with no sRGB decoding, so synthesis matches and reproduces the stored values;
float images (OpenEXR, ``.npy``, float arrays) are kept as stored. ``Exemplar.srgb`` records
which of the two a renderer is given: as Mitsuba's ``bitmap`` reads them, integer images hold
sRGB-encoded values (whatever gamma a PNG declares), float images linear ones.
"""

from __future__ import annotations

import hashlib
import math
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from warptex.exemplar_files import ExemplarError, native_order, read_image, stored_srgb
from warptex.settings import (
    MIN_EXEMPLAR_SIZE,
    check_count,
    check_file_name,
    check_flag,
    check_max_size,
    check_tileable,
)
from warptex.thread_warnings import warn

MAX_CHANNELS = 64
# Above this, an exemplar's wrap differs so much more than its neighbouring pixels that it
# is a seam, which candidates keep away from (4 bundled exemplars above it, 7 below).
SEAM_LIMIT = 2.0
# ... unless this share of neighbouring pairs of rows (columns) differ as much as the wrap:
# then the wrap falls on one of the photo's own edges, as a stripe's edge in a periodic
# pattern may, rather than on a seam. A pattern of sharp edges over 40 pixels apart has too
# few of them and is still taken for a seam, which costs little (candidates keep 2 pixels
# from the edges); `tileable=True` (`--tileable yes`) says otherwise.
SEAM_SHARE = 0.05
_SUM_CHUNK = 1 << 16  # values summed exactly at once by _mean
_REC709 = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
_SHRINK_BAND = 256  # columns shrunk at once
# sigma of the blur applied before each 2x decimation; 1 pixel suppresses aliasing while keeping
# the coarse levels close to the fine ones.
_PYRAMID_SIGMA = 1.0


# More than this share of grey pixels (neither within 10% of black nor of white) is no mask:
# anti-aliased or JPEG-compressed masks have some along their edges.
_MASK_GREY_SHARE = 0.05


class AlphaDropped(UserWarning):
    """An exemplar's alpha channel was dropped on loading (``alpha="drop"``)."""


@dataclass(frozen=True)
class PyramidLevel:
    """One level of an exemplar pyramid.

    Attributes:
        colors: ``(h, w, C)`` float32, the output channels.
        features: ``(h, w, F)`` float32, the matching channels: ``colors`` plus, if enabled, the
            feature-distance channel last.
    """

    colors: np.ndarray
    features: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """``(h, w)`` of this level."""
        return self.colors.shape[0], self.colors.shape[1]


class Exemplar:
    """A validated 2D exemplar image with any number of channels: one of Dong 2008's
    ``E_x``, ``E_y``, ``E_z`` (section 3), with its Gaussian pyramid.

    Args:
        array: ``(H, W)`` or ``(H, W, C)`` array. ``uint8``/``uint16`` are scaled to [0, 1],
            ``bool`` becomes 0/1, float data is kept as stored.
        name: what error messages and ``warptex info`` call it.
        feature_distance: optional ``(H, W)`` feature-distance channel appended to ``features``;
            see :func:`feature_distance_from_mask`.
        srgb: whether the colors are sRGB-encoded rather than linear; by default, whether
            ``array`` holds integers (see the module documentation).

    Raises:
        ExemplarError: the array cannot serve as an exemplar (see :meth:`load`).
    """

    def __init__(
        self,
        array: np.ndarray,
        *,
        name: str = "array",
        feature_distance: np.ndarray | None = None,
        srgb: bool | None = None,
    ) -> None:
        self.name = name
        self.path: Path | None = None
        self.file_shape: tuple[int, int] | None = None  # (H, W) in its file, before max_size
        # Where a feature-distance channel came from, as listings name it: "given", a mask's
        # file name (Exemplar.load), "automatic"; None without one.
        self.features_from: str | None = None if feature_distance is None else "given"
        # Whether the last color channel is the file's alpha, kept (Exemplar.load's
        # alpha="keep"): synthesized as a color, written as alpha where a format has one.
        self.kept_alpha = False
        self.colors = _validated_colors(array, name)
        self._seam_contrast: tuple[float, float] | None = None  # once: colors are read-only
        self._seams: tuple[bool, bool] | None = None
        self.srgb = stored_srgb(array) if srgb is None else check_flag("srgb", srgb)
        if feature_distance is None:
            self.features = self.colors
        else:
            distance = _validated_distance(feature_distance, self.colors.shape[:2], name)
            self.features = np.concatenate([self.colors, distance[..., None]], axis=2)
            self.features.setflags(write=False)
        if self.constant:
            warn(f"{name}: image is constant; nothing to synthesize", stacklevel=2)

    @classmethod
    def load(
        cls,
        path: str | Path,
        *,
        alpha: str = "drop",
        feature_mask: str | Path | None = None,
        feature_distance: bool | str = False,
        max_size: int | None = None,
        srgb: bool | None = None,
    ) -> Exemplar:
        """Load an exemplar from PNG, JPEG (or another Pillow format), OpenEXR or ``.npy``.

        The format is told from the file's content, not its name.

        Args:
            path: the image file.
            alpha: ``"drop"`` removes an alpha channel, with a warning unless it is opaque
                everywhere; ``"keep"`` keeps it as the last color channel.
            feature_mask: black-and-white image of the same size; pixels above half its
                maximum (in its first channel) are "feature", and a mask with many grey
                pixels is used so with a warning. Adds the feature-distance channel computed
                from it.
            feature_distance: ``"auto"`` (or True) adds a feature-distance channel from an
                automatic (Otsu) threshold of the luminance; not with a ``feature_mask``.
            max_size: shrink a larger image, and its feature mask, by area averaging until its
                larger side is ``max_size`` pixels, keeping its aspect ratio: photographs are
                often far larger than the pre-computation of candidates affords (a voxel is
                one pixel of the shrunk image). Smaller images are kept as they are.
            srgb: whether the file's colors are sRGB-encoded; by default, as Mitsuba's
                ``bitmap`` has it, those of 8- and 16-bit images are, float images' are linear.

        Raises:
            ExemplarError: missing or unreadable file, not an image, fewer than 16x16 pixels
                (after shrinking), NaN/Inf values, zero or more than 64 channels, or an
                unusable feature mask.
            TypeError: ``path`` is no file name.
            SettingError: ``max_size`` or ``srgb`` out of range or of the wrong type.
        """
        feature_distance = _checked_load_options(alpha, feature_mask, feature_distance,
                                                 max_size, srgb)
        if path == "":  # not the working folder, which Path("") names
            raise ExemplarError("the exemplar's file name is empty")
        path = check_file_name("path", path)
        # In load's own frame (not a function's), so that its warnings' stack levels stay.
        with _memory_named(path):
            array, has_alpha, file_srgb = read_image(path)
            if has_alpha and alpha == "drop":
                if array.shape[-1] == 1:
                    raise ExemplarError(f"{path}: image holds only an alpha channel (alpha='keep' "
                                        "reads it as one color channel; --alpha keep in the CLI)")
                if not _opaque(array[..., -1]):  # an alpha that is opaque everywhere says nothing
                    warn(
                        f"{path}: alpha channel dropped (alpha='keep' keeps it; --alpha keep in "
                        "the CLI)", AlphaDropped, stacklevel=2,
                    )
                array = array[..., :-1]
            read_shape = array.shape
            if max_size is not None:
                array = _shrunk(_validated_colors(array, str(path)), int(max_size), str(path))

            distance = None
            if feature_mask is not None:
                distance = _mask_distance(feature_mask, path, read_shape, array.shape, max_size)
            elif feature_distance:
                colors = _validated_colors(array, str(path))
                distance = feature_distance_from_mask(otsu_mask(colors),
                                                      name=f"{path}: automatic (Otsu)")

            # Errors name the file as given; the exemplar itself goes by its file name.
            exemplar = cls(array, name=str(path), feature_distance=distance,
                           srgb=file_srgb if srgb is None else srgb)
            exemplar.name = path.name
            exemplar.path = path.resolve()
            exemplar.file_shape = read_shape[:2]
            # A kept alpha alone is read as one color channel, as the writers take it.
            exemplar.kept_alpha = has_alpha and alpha == "keep" and exemplar.channels > 1
            if feature_mask is not None:
                exemplar.features_from = Path(feature_mask).name
            elif feature_distance:
                exemplar.features_from = "automatic"
            return exemplar

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` in pixels."""
        return self.colors.shape[0], self.colors.shape[1]

    @property
    def channels(self) -> int:
        """Number of color channels ``C`` (feature channels may be one more)."""
        return self.colors.shape[2]

    @property
    def constant(self) -> bool:
        """Whether every pixel has one color: nothing to synthesize, no variance to measure
        distances in."""
        return bool(np.all(self.colors == self.colors[:1, :1]))

    def pyramid(self, min_size: int = 8,
                seams: tuple[bool, bool] | None = None) -> list[PyramidLevel]:
        """Gaussian pyramid, coarsest level first and the exemplar itself last.

        Each coarser level blurs the finer one and keeps every second pixel, so an ``h x w``
        level becomes ``ceil(h/2) x ceil(w/2)``. The blur wraps around the borders
        (exemplars tile, §3) except across the edges that form a seam (``seams``, rows then
        columns, by default :meth:`seams`), where it reflects: no coarse pixel then mixes a
        photo's opposite edges. The pyramid stops at the first level whose larger side is at
        most ``min_size``.
        """
        check_count("min_size", min_size, low=1)
        seams = self.seams() if seams is None else seams
        levels = [PyramidLevel(self.colors, self.features)]
        while max(levels[-1].shape) > min_size:
            finer = levels[-1]
            colors = _downsample(finer.colors, seams)
            features = (colors if finer.features is finer.colors
                        else _downsample(finer.features, seams))
            levels.append(PyramidLevel(colors, features))
        return levels[::-1]

    def seam_contrast(self) -> tuple[float, float]:
        """:func:`seam_contrast_of` the exemplar's colors, computed once."""
        if self._seam_contrast is None:
            self._seam_contrast = seam_contrast_of(self.colors)
        return self._seam_contrast

    def seams(self, tileable: bool | str = "auto") -> tuple[bool, bool]:
        """Whether the (top and bottom, left and right) edges form a seam, in pixel
        coordinate order as the candidates' margins are. ``tileable`` is the setting of that
        name: ``"auto"`` decides from the photo (:func:`seams_of` its colors, computed once),
        True takes it for the paper's torus (no seam), False for a seam at every edge."""
        if check_tileable(tileable) != "auto":
            return seams_of(self.colors, tileable)
        if self._seams is None:
            self._seams = _seams(self.colors, self.seam_contrast())
        return self._seams

    def seam_problem(self) -> str | None:
        """Why the exemplar does not tile (:meth:`seams`), in words; None where it tiles."""
        seams = [f"{name} edges differ {ratio:.1f}x as much as neighbouring pixels"
                 for name, _, ratio, seam in self._edges() if seam]
        if not seams:
            return None
        return f"its {' and its '.join(seams)}"

    def own_edges(self) -> str:
        """Why edges whose :meth:`seam_contrast` is above SEAM_LIMIT form no seam, as
        clauses each starting "; "; empty where there are none."""
        return "".join(f"; its {name} edges differ {ratio:.1f}x, but at least "
                       f"{SEAM_SHARE:.0%} of its neighbouring {pairs} differ as much: the wrap "
                       "is one of the pattern's own edges"
                       for name, pairs, ratio, seam in self._edges()
                       if ratio > SEAM_LIMIT and not seam)

    def _edges(self) -> tuple[tuple[str, str, float, bool], ...]:
        """Per pair of opposite edges: its name, the neighbouring pairs compared with it,
        its :meth:`seam_contrast` and whether it is a seam."""
        across_columns, across_rows = self.seam_contrast()
        seam_rows, seam_columns = self.seams()
        return (("left and right", "columns", across_columns, seam_columns),
                ("top and bottom", "rows", across_rows, seam_rows))

    def __setstate__(self, state: dict) -> None:
        # Unpickled (compare sends exemplars to its worker processes), arrays come back
        # writable; the seams this object caches hold only while they are not.
        self.__dict__.update(state)
        self.colors.setflags(write=False)
        self.features.setflags(write=False)

    def digest(self) -> str:
        """SHA-256 hex digest of the content (shapes, dtype, colors, features), not of the path."""
        sha = hashlib.sha256(b"warptex-exemplar-v1")
        for array in (self.colors, self.features):
            sha.update(repr((array.shape, array.dtype.str)).encode())
            sha.update(np.ascontiguousarray(array).tobytes())
        return sha.hexdigest()

    def __repr__(self) -> str:
        h, w = self.shape
        extra = self.features.shape[2] - self.channels
        return (
            f"Exemplar({self.name!r}, {w}x{h}, channels={self.channels}"
            f"{', feature_distance=True' if extra else ''}{', linear' if not self.srgb else ''})"
        )


def as_exemplar(source: Exemplar | str | os.PathLike) -> Exemplar:
    """``source`` if it is an Exemplar, else the image file it names, loaded; a TypeError
    for anything else."""
    if isinstance(source, Exemplar):
        return source
    if isinstance(source, str | os.PathLike):
        return Exemplar.load(source)
    hint = (" (an array becomes one as warptex.Exemplar(array))"
            if isinstance(source, np.ndarray) else "")
    raise TypeError(f"an exemplar must be a warptex.Exemplar or an image path, got "
                    f"{type(source).__name__}{hint}")


def seam_contrast_of(colors: np.ndarray) -> tuple[float, float]:
    """How much more an (H, W, C) image's colors change across its wrap than between
    neighbouring pixels: from the last column to the first, and from the last row to the
    first. Near 1 where the photo tiles. The paper's exemplars are tori (§3, §4); above
    SEAM_LIMIT :func:`seams_of` names the edges that candidates keep away from
    (BENCHMARKS.md, "Exemplars that do not tile").

    The means do not depend on the order a machine would sum in, so the candidates that
    follow from them are the same on every CPU, also at the limit."""
    c = np.asarray(colors, dtype=np.float64)
    across = (_mean(np.abs(c[:, 0] - c[:, -1])), _mean(np.abs(c[0] - c[-1])))
    inside = (_mean(np.abs(np.diff(c, axis=1))), _mean(np.abs(np.diff(c, axis=0))))
    columns, rows = (float(a / max(i, 1e-12)) for a, i in zip(across, inside, strict=True))
    return columns, rows


def seams_of(colors: np.ndarray, tileable: bool | str = "auto") -> tuple[bool, bool]:
    """Whether an (H, W, C) image's (top and bottom, left and right) edges form a seam:
    their :func:`seam_contrast_of` is above SEAM_LIMIT, and fewer than SEAM_SHARE of the
    image's neighbouring rows (columns) differ on average as much as its last and first.
    Unless the setting ``tileable`` says: True none (the paper's torus), False all."""
    if check_tileable(tileable) != "auto":
        return not tileable, not tileable
    return _seams(colors, seam_contrast_of(colors))


def _seams(colors: np.ndarray, contrast: tuple[float, float]) -> tuple[bool, bool]:
    across_columns, across_rows = contrast
    return (across_rows > SEAM_LIMIT and _wrap_stands_out(colors, 0),
            across_columns > SEAM_LIMIT and _wrap_stands_out(colors, 1))


def _wrap_stands_out(colors: np.ndarray, axis: int) -> bool:
    """Whether fewer than SEAM_SHARE of the pairs of neighbouring rows (``axis`` 0) or
    columns (1) differ on average as much as the last and the first; summed exactly, so that
    ties, which periodic patterns make, are ties on every CPU."""
    c = np.moveaxis(np.asarray(colors, dtype=np.float64), axis, 0)
    across = _mean(np.abs(c[0] - c[-1]))
    as_large = sum(_mean(pair) >= across for pair in np.abs(np.diff(c, axis=0)))
    return as_large < SEAM_SHARE * (len(c) - 1)


def wrapping_edges(seams: tuple[bool, bool], shape: tuple[int, int],
                   size: int) -> tuple[bool, bool]:
    """Whether ``size`` x ``size`` neighbourhoods of an exemplar (or pyramid level) of
    ``shape`` wrap around its (top and bottom, left and right) edges: where these tile, as
    the paper's tori do (§3), and where a seam (:meth:`Exemplar.seams`) would leave fewer
    than ``size`` unwrapped neighbourhoods across that side."""
    (rows, columns), (height, width) = seams, shape
    return not rows or height - size + 1 < size, not columns or width - size + 1 < size


def axis_triple(x: Any, y: Any = None, z: Any = None) -> tuple[Any, Any, Any]:
    """The exemplars (or their files) of the x, y and z axes from those given, as the
    commands' --ey/--ez and precompute read them: y's defaults to x's, z's to y's (Dong
    2008, section 4, takes one exemplar per axis, as Kopf 2007, section 6.2, does)."""
    y = x if y is None else y
    return x, y, y if z is None else z


def axis_exemplars(x: Exemplar | str | os.PathLike, y: Exemplar | str | os.PathLike | None = None,
                   z: Exemplar | str | os.PathLike | None = None) -> list[Exemplar]:
    """The exemplars of the x, y and z axes as :func:`axis_triple` takes them, each file
    loaded once however many axes it serves (:func:`loaded_once`)."""
    return loaded_once(axis_triple(x, y, z))


def loaded_once(sources: Sequence[Exemplar | str | os.PathLike | None]) -> list[Exemplar | None]:
    """``sources`` as Exemplars (:func:`as_exemplar`; None stays None), each file or object
    loaded once however often it is named: a file decoded, and its warnings said, once an
    axis was three times for one photo."""
    loaded: dict[object, Exemplar] = {}
    exemplars = []
    for source in sources:
        key = os.fspath(source) if isinstance(source, str | os.PathLike) else id(source)
        if source is not None and key not in loaded:
            loaded[key] = as_exemplar(source)
        exemplars.append(None if source is None else loaded[key])
    return exemplars


def check_same_channels(exemplars: Sequence[Exemplar | None]) -> None:
    """An ExemplarError naming each axis' image unless the exemplars of the three axes
    (None for an axis left unconstrained) have as many feature channels, and as many color
    channels: a voxel's triple reads a pixel of each, and its color averages theirs."""
    given = [(axis, e) for axis, e in zip("xyz", exemplars, strict=True) if e is not None]
    for kind, count in (("feature", lambda e: e.features.shape[2]),
                        ("color", lambda e: e.colors.shape[2])):
        if len({count(e) for _, e in given}) > 1:
            found = ", ".join(f"{axis} {e.path or e.name} {count(e)}" for axis, e in given)
            raise ExemplarError("the exemplars of the three axes must have the same number of "
                                f"{kind} channels; found {found}")


def file_names(exemplars: Sequence[Exemplar]) -> str:
    """The files of ``exemplars`` (their names where they have none), each once, as an
    error about them all names them."""
    return ", ".join(dict.fromkeys(str(e.path or e.name) for e in exemplars))


def srgb_encoded(exemplars: list[Exemplar], raw: str | None = "raw") -> bool:
    """Whether the exemplars of the three axes hold sRGB-encoded colors (``srgb``); an
    ExemplarError naming them where some do and others are linear, as a voxel's color
    averages colors of all three; ``raw`` names the setting that keeps values as stored,
    None where there is none."""
    if len({e.srgb for e in exemplars}) == 1:
        return exemplars[0].srgb
    kinds = ", ".join(dict.fromkeys(
        f"{e.name} {'sRGB-encoded' if e.srgb else 'linear'}" for e in exemplars))
    keep = "" if raw is None else f", or keep the values as stored ({raw})"
    raise ExemplarError(f"the exemplars' colors are encoded differently ({kinds}): convert "
                        f"one image{keep}")


def feature_distance_from_mask(mask: np.ndarray, *, name: str = "mask") -> np.ndarray:
    """Signed distance to the edges of a binary feature mask, mapped to [0, 1].

    Distances are measured between pixel centres with a half-pixel offset, so the two pixels
    either side of an edge sit at +-0.5; they are then divided by the largest magnitude and
    mapped to [0, 1]: 0.5 is the edge, above it inside features, below outside.

    Raises:
        ExemplarError: the mask has no edge (all pixels on one side).
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.all() or not mask.any():
        raise ExemplarError(f"{name}: feature mask has no edges (all pixels on one side)")
    inside = ndimage.distance_transform_edt(mask)
    outside = ndimage.distance_transform_edt(~mask)
    signed = np.where(mask, inside - 0.5, 0.5 - outside)
    return (0.5 + 0.5 * signed / np.abs(signed).max()).astype(np.float32)


def otsu_mask(colors: np.ndarray) -> np.ndarray:
    """Binary feature mask from Otsu's threshold on the luminance of ``(H, W, C)`` colors.

    Luminance is Rec. 709 of the first three channels when there are at least three, else the
    first channel.
    """
    if colors.shape[2] >= 3:
        # Term by term, not as a BLAS product, which rounds otherwise on other CPUs.
        luminance = sum(colors[..., c] * _REC709[c] for c in range(3))
    else:
        luminance = colors[..., 0]
    counts, edges = np.histogram(luminance, bins=256)
    centres = 0.5 * (edges[:-1] + edges[1:])
    weight_low = np.cumsum(counts)
    weight_high = weight_low[-1] - weight_low
    sum_low = np.cumsum(counts * centres)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean_low = sum_low / weight_low
        mean_high = (sum_low[-1] - sum_low) / weight_high
        between = weight_low * weight_high * (mean_low - mean_high) ** 2
    # Bins are half-open [edges[k], edges[k + 1]): everything from the next edge up is "feature".
    return luminance >= edges[np.argmax(np.nan_to_num(between, nan=-1.0)) + 1]


def _mean(values: np.ndarray) -> float:
    """The mean of ``values``, whatever order a machine would sum in: exactly rounded sums
    (``math.fsum``) of fixed chunks, which keep a large photo's Python floats few."""
    flat = values.ravel()
    return math.fsum(math.fsum(flat[i:i + _SUM_CHUNK].tolist())
                     for i in range(0, flat.size, _SUM_CHUNK)) / flat.size


def _size(shape: tuple[int, ...]) -> str:
    return f"{shape[1]}x{shape[0]}"


def _downsample(image: np.ndarray, seams: tuple[bool, bool]) -> np.ndarray:
    # The channel axis needs a mode too, though with sigma 0 it is never blurred.
    modes = ["reflect" if seam else "wrap" for seam in seams] + ["wrap"]
    blurred = ndimage.gaussian_filter(image, sigma=(_PYRAMID_SIGMA, _PYRAMID_SIGMA, 0), mode=modes)
    level = np.ascontiguousarray(blurred[::2, ::2])
    level.setflags(write=False)
    return level


def _shrunk(image: np.ndarray, max_size: int, name: str) -> np.ndarray:
    """``image`` (H, W[, C]) float, area-averaged down until its larger side is ``max_size``
    pixels (each side rounded to whole pixels); as it is when it fits already."""
    h, w = image.shape[:2]
    if max(h, w) <= max_size:
        return image
    shape = tuple(round(side * max_size / max(h, w)) for side in (h, w))
    if min(shape) < MIN_EXEMPLAR_SIZE:
        raise ExemplarError(f"{name}: image is {_size((h, w))} pixels, {_size(shape)} when "
                            f"shrunk to a larger side of {max_size}; at least "
                            f"{MIN_EXEMPLAR_SIZE}x{MIN_EXEMPLAR_SIZE} needed")
    # Rows first, a band of columns at a time: a whole photo in float64 would double it.
    rows = np.concatenate([_area_average(image[:, c:c + _SHRINK_BAND], shape[0])
                           for c in range(0, w, _SHRINK_BAND)], axis=1)
    both = _area_average(rows.swapaxes(0, 1), shape[1]).swapaxes(0, 1)
    out = np.ascontiguousarray(both, dtype=np.float32)
    out.setflags(write=False)
    return out


def _area_average(image: np.ndarray, new: int) -> np.ndarray:
    """``image`` area-averaged along its first axis to ``new`` rows, in float64.

    Each output row adds its input rows' shares one at a time, in the same order on every
    machine: a BLAS product would sum in its CPU kernel's order, and the exemplar, hence
    every voxel, would differ in its last bits between machines.
    """
    size = image.shape[0]
    weights = _area_weights(size, new)
    first = np.argmax(weights > 0, axis=1)
    span = int((weights > 0).sum(axis=1).max())
    out = np.zeros((new, *image.shape[1:]))
    for k in range(span):
        index = first + k
        row = np.minimum(index, size - 1)
        share = np.where(index < size, weights[np.arange(new), row], 0.0)
        out += share.reshape(-1, *[1] * (image.ndim - 1)) * image[row]
    return out


def _area_weights(size: int, new: int) -> np.ndarray:
    """(new, size) weights of area averaging: how much of output pixel i's footprint
    ``[i, i + 1) * size / new`` each input pixel ``[j, j + 1)`` covers, rows summing to 1."""
    edges = np.arange(new + 1) * (size / new)
    pixels = np.arange(size)
    overlap = (np.minimum(edges[1:, None], pixels + 1) - np.maximum(edges[:-1, None], pixels))
    return np.clip(overlap, 0.0, None) * (new / size)


def _validated_colors(array: object, name: str) -> np.ndarray:
    try:
        data = np.asarray(array)
    except (TypeError, ValueError) as error:
        raise ExemplarError(f"{name}: not an image array ({error})") from None
    if data.ndim == 0 and isinstance(array, str | os.PathLike):
        raise ExemplarError(f"{name}: an Exemplar takes an image array; Exemplar.load reads "
                            f"the file {array}")
    if data.ndim == 2:
        data = data[..., None]
    if data.ndim != 3:
        raise ExemplarError(
            f"{name}: expected an (H, W) or (H, W, C) array, got shape {data.shape}"
        )
    if data.shape[2] == 0:
        raise ExemplarError(f"{name}: image has zero channels")
    if data.shape[2] > MAX_CHANNELS:
        raise ExemplarError(
            f"{name}: image has {data.shape[2]} channels; at most {MAX_CHANNELS} are supported"
        )
    if data.shape[0] < MIN_EXEMPLAR_SIZE or data.shape[1] < MIN_EXEMPLAR_SIZE:
        raise ExemplarError(
            f"{name}: image is {_size(data.shape)} pixels; at least "
            f"{MIN_EXEMPLAR_SIZE}x{MIN_EXEMPLAR_SIZE} needed"
        )
    colors = _to_float32(data, name)
    if not np.isfinite(colors).all():
        if np.issubdtype(data.dtype, np.floating) and np.isfinite(data).all():
            raise ExemplarError(f"{name}: image holds values beyond float32's range "
                                f"(±{np.finfo(np.float32).max:.3g})")
        raise ExemplarError(f"{name}: image contains NaN or Inf values")
    colors.setflags(write=False)
    return colors


def _to_float32(data: np.ndarray, name: str) -> np.ndarray:
    data = data.astype(native_order(data.dtype), copy=False)
    if data.dtype == np.uint8:
        return data.astype(np.float32) / np.float32(255)
    if data.dtype == np.uint16:
        return data.astype(np.float32) / np.float32(65535)
    if data.dtype == np.bool_:
        return data.astype(np.float32)
    if np.issubdtype(data.dtype, np.floating):
        with np.errstate(over="ignore"):  # overflow becomes Inf, reported by the caller
            return np.array(data, dtype=np.float32)
    raise ExemplarError(f"{name}: unsupported data type {data.dtype}; use float, uint8, uint16 "
                        "or bool")


def _validated_distance(distance: np.ndarray, shape: tuple[int, int], name: str) -> np.ndarray:
    data = np.asarray(distance, dtype=np.float32)
    if data.ndim == 3 and data.shape[2] == 1:
        data = data[..., 0]
    if data.shape != shape:
        raise ExemplarError(f"{name}: feature distance has shape {data.shape}, expected {shape}")
    if not np.isfinite(data).all():
        raise ExemplarError(f"{name}: feature distance contains NaN or Inf values")
    return data


def _opaque(alpha: np.ndarray) -> bool:
    """Whether an alpha channel, as stored, is fully opaque everywhere."""
    full = np.iinfo(alpha.dtype).max if np.issubdtype(alpha.dtype, np.integer) else 1.0
    return bool(np.all(alpha >= full))


def _checked_load_options(alpha: str, feature_mask: str | Path | None,
                          feature_distance: bool | str, max_size: int | None,
                          srgb: bool | None) -> bool:
    """:meth:`Exemplar.load`'s options checked, before any file is read; whether a
    feature-distance channel is asked for."""
    if alpha not in ("drop", "keep"):
        raise ValueError(f"alpha must be 'drop' or 'keep', not {alpha!r}")
    # Not ``in (False, True, "auto")``: 1 and 0.0 equal the bools and would pass.
    if not (feature_distance == "auto" if isinstance(feature_distance, str)
            else isinstance(feature_distance, bool | np.bool_)):
        raise ValueError(
            f"feature_distance must be False, True or 'auto', not {feature_distance!r}"
        )
    if feature_mask is not None and feature_distance:
        raise ValueError("give either feature_mask or feature_distance ('auto' or True), "
                         "not both")
    check_max_size(max_size)
    if srgb is not None:
        check_flag("srgb", srgb)
    return bool(feature_distance)


def _mask_distance(feature_mask: str | Path, path: Path, read_shape: tuple[int, ...],
                   shape: tuple[int, ...], max_size: int | None) -> np.ndarray:
    """The feature-distance channel of :meth:`Exemplar.load`'s ``feature_mask`` for the
    exemplar ``path``, read at ``read_shape`` and now of ``shape`` (shrunk to ``max_size``),
    which the mask is shrunk to as well: Kopf 2007's signed feature distance, of features
    marked by hand."""
    mask_path = check_file_name("feature_mask", feature_mask)
    with _memory_named(mask_path):  # the mask's, not the exemplar's
        mask_image = read_image(mask_path)[0]
        if mask_image.shape[:2] != read_shape[:2]:
            raise ExemplarError(
                f"{mask_path}: feature mask is {_size(mask_image.shape)} pixels but "
                f"{path} is {_size(read_shape)}"
            )
        first = mask_image[..., 0] if mask_image.ndim == 3 else mask_image
        if np.issubdtype(first.dtype, np.floating) and not np.isfinite(first).all():
            # Half its maximum, the threshold, would be NaN or infinite.
            raise ExemplarError(f"{mask_path}: feature mask contains NaN or Inf values")
        _warn_unless_binary(mask_image, str(mask_path))
        if shape[:2] != read_shape[:2]:
            mask_image = _shrunk(_to_float32(mask_image, str(mask_path)), int(max_size),
                                 str(mask_path))
        return feature_distance_from_mask(_binary_mask(mask_image, str(mask_path)),
                                          name=str(mask_path))


def _warn_unless_binary(image: np.ndarray, name: str) -> None:
    """Warn where a feature mask is no black-and-white image (a photo given by mistake):
    it is thresholded at half its maximum all the same, which may mark nothing useful."""
    first = image[..., 0] if image.ndim == 3 else image
    if first.dtype == np.bool_:
        return
    values = first.astype(np.float32)
    top = float(values.max())
    grey = float(np.mean((values > 0.1 * top) & (values < 0.9 * top))) if top > 0 else 0.0
    if grey > _MASK_GREY_SHARE:
        channel = "its first channel" if image.ndim == 3 else "it"
        warn(f"{name}: not a black-and-white feature mask ({grey:.0%} of its pixels "
             f"are grey); features are marked where {channel} exceeds half its "
             "maximum", stacklevel=4)  # the caller of Exemplar.load


@contextmanager
def _memory_named(path: Path) -> Iterator[None]:
    """An image that does not fit the memory the process may use (``ulimit -v``, a batch
    job's limit) refused naming its file, not in NumPy's or Pillow's traceback."""
    try:
        yield
    except MemoryError as error:
        raise ExemplarError(f"{path}: too large to load in the memory this process may use "
                            f"({str(error) or 'out of memory'})") from None


def _binary_mask(image: np.ndarray, name: str) -> np.ndarray:
    if image.ndim == 3:
        image = image[..., 0]
    if image.dtype == np.bool_:
        return image
    values = _to_float32(image, name)
    return values > 0.5 * values.max() if values.max() > 0 else values > 0
