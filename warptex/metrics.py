"""Quality metrics of solid textures against their exemplar (Dong 2008, section 6.3).

The metrics look at axis-aligned slices, the way a viewer judges a cut: a slice
perpendicular to axis k is read with the same orientation as the exemplar of axis k
(volume axes k+1, k+2 as its rows and columns; see ``warptex.candidates``).
"""

from __future__ import annotations

import os
from numbers import Integral

import numpy as np
from scipy.spatial import cKDTree

from warptex.exemplar import Exemplar, seams_of, wrapping_edges
from warptex.settings import check_count


def axis_slices(volume: np.ndarray, axis: int, count: int = 8) -> list[np.ndarray]:
    """``count`` evenly spaced slices perpendicular to ``axis``, as (rows, cols, C) images
    oriented like the exemplar of that axis."""
    _check_axis(axis)
    check_count("count (of slices)", count, low=1)
    depth = volume.shape[axis]
    picks = np.unique(np.linspace(0, depth - 1, min(count, depth)).astype(int))
    order = [(axis + 1) % 3, (axis + 2) % 3]
    out = []
    for i in picks:
        s = np.take(volume, i, axis=axis)
        # np.take drops `axis`; remaining axes are the other two in increasing order.
        remaining = [a for a in range(3) if a != axis]
        out.append(np.transpose(s, [remaining.index(order[0]), remaining.index(order[1]), 2]))
    return out


def patches(image: np.ndarray, size: int, stride: int = 1,
            wrap: bool | tuple[bool, bool] = False) -> np.ndarray:
    """All ``size`` x ``size`` patches of an (H, W, C) image as rows (n, size*size*C);
    ``wrap`` (for rows and columns, or one for both) lets them wrap around the edges."""
    wrap_rows, wrap_cols = (wrap, wrap) if np.ndim(wrap) == 0 else wrap
    h, w, c = image.shape
    image = np.pad(image, ((0, size - 1 if wrap_rows else 0), (0, size - 1 if wrap_cols else 0),
                           (0, 0)), mode="wrap")
    h2, w2 = (h if wrap_rows else h - size + 1), (w if wrap_cols else w - size + 1)
    win = np.lib.stride_tricks.sliding_window_view(image, (size, size), axis=(0, 1))
    win = win[:h2:stride, :w2:stride]
    return win.transpose(0, 1, 3, 4, 2).reshape(-1, size * size * c).astype(np.float32)


def exemplar_patches(exemplar: Exemplar | np.ndarray, size: int,
                     tileable: bool | str = "auto") -> np.ndarray:
    """The exemplar's ``size`` x ``size`` patches, the neighbourhoods a slice is measured
    against: they wrap around the edges that tile (the paper's tori, Dong 2008 §3) but not
    across a photo's seam (:func:`warptex.exemplar.seams_of`, or as the setting ``tileable``
    says), where a wrapped patch is no part of the photo
    (:func:`warptex.exemplar.wrapping_edges`)."""
    colors = _colors(exemplar)
    # An Exemplar has decided its seams once; an array (or a pyramid level) is measured here.
    seams = (exemplar.seams(tileable) if isinstance(exemplar, Exemplar)
             else seams_of(colors, tileable))
    return patches(colors, size, wrap=wrapping_edges(seams, colors.shape[:2], size))


def _checked(volume, exemplar, axis: int, size: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``volume`` (D, H, W, C) and ``exemplar`` (H, W, C, or a warptex.Exemplar) as float
    arrays of the same channels, whose slices across ``axis`` hold ``size`` x ``size``
    patches; else a ValueError or TypeError saying which argument is wrong."""
    exemplar = _colors(exemplar)
    volume = np.asarray(volume)
    if volume.ndim != 4:
        raise ValueError(f"volume must be a (D, H, W, C) array, got shape {volume.shape}")
    if exemplar.ndim != 3:
        raise ValueError(f"exemplar must be an (H, W, C) image, got shape {exemplar.shape}")
    for name, a in (("volume", volume), ("exemplar", exemplar)):
        if not np.issubdtype(a.dtype, np.floating):
            raise TypeError(f"{name} must hold float colors (as warptex loads them), got "
                            f"{a.dtype}")
    if volume.shape[3] != exemplar.shape[2]:
        raise ValueError(f"volume has {volume.shape[3]} channels, exemplar "
                         f"{exemplar.shape[2]}")
    _check_axis(axis)
    if isinstance(size, bool) or not isinstance(size, Integral) or size < 1:
        raise ValueError(f"size (of the patches) must be a positive integer, got {size!r}")
    across = [volume.shape[a] for a in range(3) if a != axis]
    if min(across) < size or volume.shape[axis] < 1:
        raise ValueError(f"slices across axis {axis} are {across[0]} x {across[1]}, "
                         f"{volume.shape[axis]} of them: too few or too small for {size} x "
                         f"{size} patches")
    for name, a in (("volume", volume), ("exemplar", exemplar)):
        if not np.isfinite(a).all():
            raise ValueError(f"{name} holds NaN or infinite values")
    # Distances are measured in units of the exemplar's spread: a flat one has none.
    if not _variance(exemplar) > 0:
        raise ValueError("exemplar is constant: the metrics measure in units of its variance")
    return volume, exemplar


def _colors(exemplar: np.ndarray | Exemplar) -> np.ndarray:
    """The colors of an exemplar given as an array or an Exemplar; a file name is refused
    rather than taken for a 0-d array."""
    if isinstance(exemplar, str | os.PathLike):
        raise TypeError(f"exemplar must be an (H, W, C) image array or a warptex.Exemplar "
                        f"(Exemplar.load reads a file), got {exemplar!r}")
    return np.asarray(getattr(exemplar, "colors", exemplar))


def _check_axis(axis: object) -> None:
    if isinstance(axis, bool) or not isinstance(axis, Integral) or axis not in (0, 1, 2):
        raise ValueError(f"axis must be 0, 1 or 2, got {axis!r}")


def _variance(exemplar: np.ndarray) -> float:
    """The exemplar's variance summed over channels: the unit of the distances measured."""
    return float(exemplar.reshape(-1, exemplar.shape[2]).var(axis=0).sum())


def neighborhood_energy(
    volume: np.ndarray, exemplar: np.ndarray | Exemplar, axis: int, size: int = 5,
    slices: int = 8, tileable: bool | str = "auto",
) -> float:
    """Mean squared distance from each slice patch to its nearest exemplar patch
    (:func:`exemplar_patches` under the setting ``tileable``), normalized by the exemplar's
    variance and patch size (0 = every patch is in the exemplar; about 2 for patches of
    unrelated values of the same variance)."""
    volume, colors = _checked(volume, exemplar, axis, size)
    check_count("slices", slices, low=1)
    tree = cKDTree(exemplar_patches(exemplar, size, tileable))
    vol_patches = np.concatenate(
        [patches(s, size, stride=2) for s in axis_slices(volume, axis, slices)]
    )
    dist, _ = tree.query(vol_patches, k=1, workers=-1)
    return float(np.mean(dist**2) / (size * size * _variance(colors)))


def worst_axis_energy(volume: np.ndarray, exemplar: np.ndarray | Exemplar,
                      tileable: bool | str = "auto") -> float:
    """The largest of the three axes' :func:`neighborhood_energy`: a solid texture is
    judged by its worst cut (the measure Dong 2008, section 6.3, compares)."""
    return max(neighborhood_energy(volume, exemplar, axis, tileable=tileable)
               for axis in range(3))


def sliced_wasserstein(
    volume: np.ndarray,
    exemplar: np.ndarray | Exemplar,
    axis: int,
    size: int = 5,
    directions: int = 64,
    slices: int = 8,
    seed: int = 0,
    tileable: bool | str = "auto",
) -> float:
    """Sliced Wasserstein-1 distance between slice patches and exemplar patches
    (:func:`exemplar_patches` under the setting ``tileable``), averaged over random unit
    directions and normalized by the exemplar's std."""
    volume, colors = _checked(volume, exemplar, axis, size)
    check_count("directions", directions, low=1)
    check_count("slices", slices, low=1)
    check_count("seed", seed)
    a = np.concatenate([patches(s, size, stride=2) for s in axis_slices(volume, axis, slices)])
    b = exemplar_patches(exemplar, size, tileable)
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(a.shape[1], directions)).astype(np.float32)
    dirs /= np.linalg.norm(dirs, axis=0, keepdims=True)
    q = np.linspace(0.0, 1.0, 257)
    pa = np.quantile(a @ dirs, q, axis=0)
    pb = np.quantile(b @ dirs, q, axis=0)
    return float(np.mean(np.abs(pa - pb)) / np.sqrt(_variance(colors)))


def histogram_distance(volume: np.ndarray, exemplar: np.ndarray, axis: int,
                       bins: int = 16) -> float:
    """Mean over channels of the L1 distance between normalized ``bins``-bin histograms of
    the slices perpendicular to ``axis`` and of the exemplar (0 = same, 2 = disjoint)."""
    volume, exemplar = _checked(volume, exemplar, axis)
    check_count("bins", bins, low=1)
    slices = axis_slices(volume, axis)
    values = np.concatenate([s.reshape(-1, s.shape[2]) for s in slices])
    ref = exemplar.reshape(-1, exemplar.shape[2])
    total = 0.0
    for c in range(ref.shape[1]):
        lo, hi = float(ref[:, c].min()), float(ref[:, c].max())
        hi = hi if hi > lo else lo + 1.0
        a, _ = np.histogram(np.clip(values[:, c], lo, hi), bins=bins, range=(lo, hi))
        b, _ = np.histogram(ref[:, c], bins=bins, range=(lo, hi))
        total += float(np.abs(a / a.sum() - b / b.sum()).sum())
    return total / ref.shape[1]


def repetition_score(image: np.ndarray, exclude: int = 8) -> float:
    """Highest normalized autocorrelation of a large slice at shifts farther than
    ``exclude`` pixels: near 1 for a tiled texture, low when nothing repeats. ``image`` is
    (H, W) or (H, W, C); shifts up to a quarter of it count, so it must be at least
    ``4 * (exclude + 1)`` pixels along one side."""
    image = np.asarray(image)
    image = image[:, :, None] if image.ndim == 2 else image
    if image.ndim != 3:
        raise ValueError(f"image must be (H, W) or (H, W, C), got shape {image.shape}")
    if not np.isfinite(image).all():
        raise ValueError("image holds NaN or infinite values")
    check_count("exclude", exclude)  # shift 0 always matches itself
    if max(image.shape[:2]) // 4 <= exclude:
        raise ValueError(f"a {image.shape[0]} x {image.shape[1]} image is too small for the "
                         f"repetition score: shifts past {exclude} pixels up to a quarter of "
                         f"it need more than {4 * (exclude + 1) - 1} pixels along a side")
    x = image - image.mean(axis=(0, 1))
    spectrum = np.fft.rfft2(x, axes=(0, 1))
    corr = np.fft.irfft2(np.abs(spectrum) ** 2, s=x.shape[:2], axes=(0, 1)).sum(axis=2)
    if corr[0, 0] <= 0:
        return 0.0
    corr /= corr[0, 0]
    h, w = corr.shape
    dy = np.minimum(np.arange(h), h - np.arange(h))[:, None]
    dx = np.minimum(np.arange(w), w - np.arange(w))[None, :]
    # Circular correlation pairs a shift with its complement, and near half the slice the
    # overlap of a pattern with itself wraps around: only shifts up to a quarter count.
    valid = (np.maximum(dy, dx) > exclude) & (dy <= h // 4) & (dx <= w // 4)
    return float(corr[valid].max())


# Reference volumes: where each metric should find a solid texture worst, so that tests and
# comparisons can check the metrics against them.


def iid_noise(exemplar: np.ndarray | Exemplar, shape: tuple[int, int, int],
              seed: int = 0) -> np.ndarray:
    """A volume of independent exemplar pixels: right histogram, no structure."""
    exemplar = _colors(exemplar)
    flat = exemplar.reshape(-1, exemplar.shape[2])
    idx = np.random.default_rng(seed).integers(0, len(flat), size=int(np.prod(shape)))
    return flat[idx].reshape(*shape, exemplar.shape[2])


def extrusion(exemplar: np.ndarray | Exemplar, depth: int, axis: int = 2) -> np.ndarray:
    """The exemplar stacked along ``axis``: perfect on that axis' slices, streaks elsewhere."""
    exemplar = _colors(exemplar)
    _check_axis(axis)
    order = [(axis + 1) % 3, (axis + 2) % 3]
    vol = np.repeat(exemplar[None], depth, axis=0)  # (depth, rows, cols, C)
    dest = [axis, *order]
    return np.moveaxis(vol, [0, 1, 2], dest)
