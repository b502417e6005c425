"""Solid texture synthesis by global texture optimization (Kopf et al. 2007), as a baseline.

Unlike lazy synthesis, this method synthesizes a whole periodic (toroidal) volume at once. It
minimizes the texture energy of equation 1, the sum over voxels ``v`` and axes ``i`` of
``|s_v,i - e_v,i|^r`` (r = 0.8) between the 8x8 neighbourhood ``s_v,i`` of ``v`` in the slice
perpendicular to axis ``i`` and its best-matching exemplar window ``e_v,i``, on a three-level
pyramid (section 4), alternating

- the search phase (section 4.2): windows are PCA-projected to 95% of their variance and
  matched with an approximate nearest-neighbour search, only at the centres of the sparser
  grid (m = 2);
- the optimization phase (section 4.1): iteratively re-weighted least squares, each voxel the
  weighted average of the texels the matched windows put on it, with weights re-weighted by
  histogram matching (section 5) against 16-bin per-channel histograms that are kept current
  as voxels change, in random order.

The approximate search is SciPy's ``cKDTree`` with ``eps = 2``: like the ANN library of Mount
and Arya the paper uses (and its value, ``eps = 2``), a k-d tree that returns a neighbour
within ``(1 + eps)`` times the distance of the nearest one. Since a new match only replaces
the current one when closer, searches after the first of a level are bounded by the current
match's distance, which prunes part of the tree (1.2-1.7x faster measured at 64^3).
With ``mean_shift``, a voxel averages only the texels of the dominant cluster (section
4.1): mean shift with a flat kernel, started at the texel with the most weight within the
bandwidth, whose bandwidth shrinks over each level's iterations from a plain average towards
a single colour.

Exemplars are tori, as the paper's are, except that where a photo does not tile
(:meth:`warptex.Exemplar.seams`, or as the setting ``tileable`` says) no window wraps across
its seam, in the search as in the metrics (:func:`warptex.metrics.exemplar_patches`): the
seam is not part of the photo.

Axis ``i`` of the volume (of the ``(X, Y, Z, C)`` result) is constrained by its
own exemplar (section 6.2), oriented as in :mod:`warptex.metrics`: slices perpendicular to
axis ``i`` have volume axes ``i+1`` and ``i+2`` as the exemplar's rows and columns. One axis
may be left unconstrained.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path

import numpy as np
import warp as wp
from scipy.spatial import cKDTree
from tqdm import tqdm

from kernels import kopf as _k
from warptex.exemplar import (
    Exemplar,
    check_same_channels,
    file_names,
    loaded_once,
    wrapping_edges,
)
from warptex.parallel import kd_tree, launch_ranges, nearest
from warptex.settings import check_flag, check_settings, is_integer
from warptex.thread_warnings import warn
from warptex.warp_runtime import init_warp, launch

LEVELS = 3  # "we use a three-level synthesis pyramid" (section 6)
R = 0.8  # robust exponent of equation 1
GRID_SPACING = 2  # m of section 4.2; the kernels' grid indexing assumes 2
VARIANCE_KEPT = 0.95  # PCA coefficients kept (section 4.2)
ANN_EPS = 2.0  # "eps = 2 to be a good compromise between speed and accuracy" (section 4.2)
BINS = 16  # histogram bins per channel (section 5)
# Histograms are refreshed this many times per optimization phase. Updating them once per
# iteration overshoots (section 5); between refreshes only 1/64 of the voxels change, while
# each batch is still large enough to run in parallel.
HISTOGRAM_REFRESHES = 64
# Floor on |s_v,i - e_v,i| in the IRLS weight: a window that matches exactly would otherwise
# get infinite weight. Far below the distance of any two distinct 8x8 windows of [0, 1] data.
MIN_DISTANCE = 1e-3
_DEVICE = "cpu"  # the ANN search runs on the host; the solid is shared with it without copies
_BOUND_GROUPS = 16  # groups of queries sharing one distance bound in _ann_search
# NumPy's 8-byte temporaries at a time, in rows of voxels: the bounded search's differences
# to the current matches, the histograms' bin indices. All at once, either would be a level's
# peak.
_PART_BYTES = 1 << 20
# Mean-shift bandwidth at a level's first and last iteration, in units of the standard
# deviation of the level's exemplar texels (geometric in between): "gradually reduced as the
# optimization of each resolution level progresses" (section 4.1).
MEAN_SHIFT_BANDWIDTH = (1.0, 0.25)
# Peak memory of a synthesis per voxel, beside the solid and its returned copy: most of it the
# search's PCA coefficients (MAX_COEFFS float32 per grid centre, a quarter of the voxels: 96
# bytes a voxel). Resident peaks beyond the volume and its copy, two iterations a level,
# search structures included (benchmarks/bench_kopf_memory.py, BENCHMARKS.md, 2026-12-07):
# 131 bytes a voxel at 64^3 (granite_64), 126 and 117 for 3 and 8 channels of noise, which
# keeps every coefficient; 106 to 112 at 128^3.
WORK_BYTES_PER_VOXEL = 300
# Peak memory of an exemplar's search structure per window (pixel) while it is built: its
# float64 window of 64 values per feature, centred in place, beside its coefficients (at most
# MAX_COEFFS float64) and the tree over them, which are kept for the level (the coarser level's,
# a quarter as large, still held); and, once per exemplar, the (64 F)^2 covariance with the
# eigensolver's copies of it. Measured with tracemalloc, every window kept (no seam): 1,663
# bytes a pixel (rust_256, 13 coefficients), 2,066 (granite_64, 48), 5,528 (8 random
# channels at 64x64, 96); BENCHMARKS.md, with seams. What tracemalloc does not see (the
# allocator's and BLAS's own memory, the tree's C++ nodes) grows with the pixels too, and
# the resident peak of a fresh process exceeded the count by 3.0 to 6.3 MiB at 16^2 to
# 128^2 pixels (benchmarks/bench_kopf_search_memory.py): 8 MiB on top, once.
SEARCH_BYTES_PER_FEATURE = 512
SEARCH_BYTES_PER_WINDOW = 8 * _k.MAX_COEFFS + 512
SEARCH_COVARIANCES = 3
SEARCH_BYTES_UNTRACED = 8 << 20


@dataclass(frozen=True)
class Iteration:
    """Progress of one search + optimization iteration.

    Attributes:
        level: pyramid level, 0 the coarsest.
        iteration: index within the level.
        energy: texture energy (equation 1) of the solid entering this iteration's
            optimization phase, with the matches its search phase found, as the mean of
            ``|s_v,i - e_v,i|^r`` over the grid centres of the constrained axes.
        seconds: wall time of the iteration.
    """

    level: int
    iteration: int
    energy: float
    seconds: float


@dataclass
class _Axis:
    """One constrained axis at one level: its exemplar and its search structure."""

    features: np.ndarray  # (h, w, F)
    window_pixels: np.ndarray  # (windows,) int32 exemplar pixel each tree window is centred on
    mean: np.ndarray  # (64 F,) mean window
    basis: np.ndarray  # (64 F, MAX_COEFFS) PCA basis, zero past the kept coefficients
    dims: int
    tree: cKDTree
    # Coefficients that hold VARIANCE_KEPT of the variance: more than dims where the kernels
    # hold fewer (then warned of, with ``kept``, the share of the variance that dims hold).
    needed: int
    kept: float


def check_size(size: int) -> None:
    """Raise ValueError unless ``size`` halves evenly through the pyramid's levels."""
    if not is_integer(size):
        raise TypeError(f"size must be an integer, got {size!r}")
    if size < 1 or size % (1 << LEVELS) != 0:
        raise ValueError(f"size must be a positive multiple of {1 << LEVELS} for Kopf's method "
                         f"(its {LEVELS} levels halve it, the coarsest onto an even grid), "
                         f"got {size}")


def working_bytes(size: int) -> int:
    """About the most memory :func:`synthesize` takes for a ``size^3`` solid beside the
    solid and its result, whatever the exemplar (``WORK_BYTES_PER_VOXEL``)."""
    return size**3 * WORK_BYTES_PER_VOXEL


def search_bytes(exemplars: Sequence[Exemplar | None]) -> int:
    """About the most memory the search structures of ``exemplars`` (one per axis, None
    for a free one) take, at the finest level, where they are largest: it grows with the
    exemplars' pixels, not with the solid's size."""
    distinct = {id(e): e for e in exemplars if e is not None}.values()
    total = SEARCH_BYTES_UNTRACED if distinct else 0
    for e in distinct:
        features = e.features.shape[2]
        total += (e.shape[0] * e.shape[1] * (SEARCH_BYTES_PER_FEATURE * features
                                            + SEARCH_BYTES_PER_WINDOW)
                  + SEARCH_COVARIANCES * 8 * (_k.WINDOW * _k.WINDOW * features) ** 2)
    return total


def synthesize(
    exemplar: Exemplar | str | Path | None,
    size: int = 64,
    iterations: int | Sequence[int] = (6, 4, 3),
    seed: int = 0,
    progress: bool = True,
    *,
    exemplars: Sequence[Exemplar | str | Path | None] | None = None,
    histogram_matching: bool = True,
    mean_shift: bool = False,
    tileable: bool | str = "auto",
    on_iteration: Callable[[Iteration], None] | None = None,
) -> np.ndarray:
    """Synthesize a periodic ``size^3`` solid texture (Kopf et al. 2007).

    Args:
        exemplar: the exemplar of all three axes (or its image file); ``None`` when
            ``exemplars`` is given.
        size: edge of the cubic volume in voxels, a multiple of 8 (the coarsest of the three
            levels must have even size for the m = 2 grid).
        iterations: search + optimization iterations per level, coarsest first, or one count
            for every level.
        seed: seed of the random initial solid and of the voxel visiting order.
        progress: show a progress bar.
        exemplars: per-axis exemplars ``(ex, ey, ez)`` (section 6.2); ``None`` leaves that axis
            unconstrained. At least two must be given and all must have the same channels.
        histogram_matching: re-weight by histograms (section 5).
        mean_shift: average only the dominant cluster of each voxel's texels (section 4.1),
            which keeps edges sharp where plain averaging blurs them.
        tileable: the setting of that name (:meth:`warptex.Exemplar.seams`): ``"auto"``
            leaves out the windows that wrap across a photo's seam, True takes every
            exemplar for the paper's torus, False lets no window wrap.
        on_iteration: called after every iteration with its :class:`Iteration`.

    Returns:
        ``(size, size, size, C)`` float32 colors; a feature-distance channel, if the exemplars
        have one, is synthesized along but not returned.
    """
    check_size(size)
    size = int(size)  # a NumPy integer's n**3 would wrap
    check_settings(seed=seed)
    for name, flag in (("progress", progress), ("histogram_matching", histogram_matching),
                       ("mean_shift", mean_shift)):
        check_flag(name, flag)  # "no" would count as true
    if on_iteration is not None and not callable(on_iteration):  # not after a level's work
        raise TypeError(f"on_iteration must be a function or None, got {on_iteration!r}")
    counts = _iteration_counts(iterations)
    axes = _axis_exemplars(exemplar, exemplars)
    # One pyramid (and below, one search structure) per distinct exemplar.
    distinct = {id(e): e for e in axes if e is not None}
    seams = {k: e.seams(tileable) for k, e in distinct.items()}
    axis_seams = [None if e is None else seams[id(e)] for e in axes]
    init_warp()
    pyramids = {k: e.pyramid(min_size=1, seams=seams[k])[-LEVELS:] for k, e in distinct.items()}
    rng = np.random.default_rng(seed)
    solid = None
    short: dict[str, str] = {}  # what each level's PCA kept where it held less than the paper's
    with tqdm(total=sum(counts), desc="kopf", unit="it", disable=not progress) as bar:
        for level in range(LEVELS):
            n = size >> (LEVELS - 1 - level)
            level_feats = {k: np.ascontiguousarray(p[level].features)
                           for k, p in pyramids.items()}
            feats = [None if e is None else level_feats[id(e)] for e in axes]
            solid = _random_solid(feats, n, rng) if solid is None else _upsample(solid, n // 2)
            optimizer = _LevelOptimizer(feats, axis_seams, solid, histogram_matching)
            short |= _pca_shortfall(axes, optimizer, level)
            bandwidths = _bandwidths(optimizer.spread, counts[level]) if mean_shift else None
            for it in range(counts[level]):
                start = time.perf_counter()
                energy = optimizer.search()
                optimizer.optimize(rng.permutation(n**3).astype(np.int32),
                                   0.0 if bandwidths is None else bandwidths[it])
                bar.update()
                if on_iteration is not None:
                    on_iteration(Iteration(level, it, energy, time.perf_counter() - start))
    if short:  # a baseline that keeps less than the paper's share says so, once
        warn("Kopf's PCA keeps fewer coefficients than section 4.2 asks of the exemplars' "
             "windows: " + "; ".join(f"{where}: {kept}" for where, kept in short.items()),
             stacklevel=2)
    channels = next(e for e in axes if e is not None).channels
    return solid.numpy().reshape(size, size, size, -1)[..., :channels].copy()


def _iteration_counts(iterations: int | Sequence[int]) -> list[int]:
    """``synthesize``'s ``iterations`` as one count per level, coarsest first."""
    counts = [iterations] * LEVELS if np.ndim(iterations) == 0 else list(iterations)
    if len(counts) != LEVELS or not all(is_integer(t) and t >= 1 for t in counts):
        raise ValueError(f"iterations must be a positive integer or {LEVELS} of them, one per "
                         f"level, got {iterations!r}")
    return [int(t) for t in counts]


def _pca_shortfall(axes: Sequence[Exemplar | None], optimizer: _LevelOptimizer,
                   level: int) -> dict[str, str]:
    """Per exemplar whose windows at ``level`` need more PCA coefficients than the kernels
    hold (section 4.2's 95 % of the variance), what they keep."""
    return {f"{e.path or e.name} at level {level}":
            f"{ax.dims} dimensions, {ax.kept:.1%} of the variance; "
            f"{VARIANCE_KEPT:.0%} needs {ax.needed}"
            for e, ax in zip(axes, optimizer.axes, strict=True)
            if ax is not None and ax.needed > ax.dims}


def _axis_exemplars(
    exemplar: Exemplar | str | Path | None,
    exemplars: Sequence[Exemplar | str | Path | None] | None,
) -> list[Exemplar | None]:
    if (exemplar is None) == (exemplars is None):
        raise ValueError("give either exemplar or exemplars (one per axis), not both or neither")
    if exemplars is not None and (isinstance(exemplars, Exemplar | str | Path)
                                  or not isinstance(exemplars, Sequence)):
        raise TypeError("exemplars must be a sequence of three exemplars (x, y, z), got "
                        f"{type(exemplars).__name__}; one exemplar for every axis is exemplar")
    axes = [exemplar] * 3 if exemplars is None else list(exemplars)
    if len(axes) != 3:
        raise ValueError(f"exemplars must have three entries (x, y, z), got {len(axes)}")
    axes = loaded_once(axes)
    given = [e for e in axes if e is not None]
    if len(given) < 2:
        raise ValueError("at least two axes must be constrained by an exemplar")
    check_same_channels(axes)
    check_channels(axes)
    return axes


def check_channels(exemplars: Sequence[Exemplar | None]) -> None:
    """Raise ValueError, naming the files, unless the matching channels of ``exemplars``
    (one per axis, None for a free one) are few enough for the search's windows."""
    given = [e for e in exemplars if e is not None]
    if given and given[0].features.shape[2] > _k.MAX_FEATURES:
        what = " (colors and a feature distance)" if given[0].features_from else ""
        raise ValueError(f"{file_names(given)}: {given[0].features.shape[2]} matching "
                         f"channels{what}; "
                         f"Kopf's method handles at most {_k.MAX_FEATURES}")


def _bandwidths(spread: float, iterations: int) -> np.ndarray:
    """Mean-shift bandwidth of each iteration of a level (``MEAN_SHIFT_BANDWIDTH``)."""
    first, last = MEAN_SHIFT_BANDWIDTH
    steps = np.linspace(0.0, 1.0, iterations) if iterations > 1 else np.ones(1)
    return spread * first * (last / first) ** steps


def _random_solid(feats: list[np.ndarray | None], n: int, rng: np.random.Generator) -> wp.array:
    """Voxels "randomly chosen from the exemplar" (section 4), pooled over the constrained
    axes' exemplars."""
    pool = np.concatenate([f.reshape(-1, f.shape[2]) for f in feats if f is not None])
    return wp.array(pool[rng.integers(0, len(pool), n**3)], dtype=wp.float32, device=_DEVICE)


def _upsample(coarse: wp.array, n: int) -> wp.array:
    fine = wp.empty(((2 * n) ** 3, coarse.shape[1]), dtype=wp.float32, device=_DEVICE)
    launch(_k.upsample_trilinear, fine.shape[0], [coarse, n], [fine], device=_DEVICE)
    return fine


def _windows(features: np.ndarray, seams: tuple[bool, bool]) -> tuple[np.ndarray, np.ndarray]:
    """The exemplar's 8x8 windows, ``(windows, 64 F)`` ordered ``(a * 8 + b) * F + f`` like
    the kernels, and the pixel ``u*w + v`` each is centred on. They wrap around the edges
    that tile (toroidal), not across a photo's seam (``seams``, rows then columns, from
    :meth:`Exemplar.seams`), where a wrapped window is no part of the photo
    (:func:`warptex.exemplar.wrapping_edges`)."""
    h, w, nfeat = features.shape
    wrap_rows, wrap_cols = wrapping_edges(seams, (h, w), _k.WINDOW)
    rows = np.flatnonzero(_window_centres(h, wrap_rows))
    cols = np.flatnonzero(_window_centres(w, wrap_cols))
    # Filled shift by shift, at the kept centres only: the 64 shifted copies held at once,
    # or all windows and then the kept ones, doubled the peak memory.
    windows = np.empty((len(rows), len(cols), _k.WINDOW * _k.WINDOW, nfeat), features.dtype)
    kept = np.ix_(rows, cols)
    for a in range(_k.WINDOW):
        for b in range(_k.WINDOW):
            shifted = np.roll(features, (_k.HALF - a, _k.HALF - b), axis=(0, 1))
            windows[:, :, a * _k.WINDOW + b] = shifted[kept]
    pixels = (rows[:, None] * w + cols[None, :]).reshape(-1).astype(np.int32)
    return windows.reshape(len(pixels), _k.WINDOW * _k.WINDOW * nfeat), pixels


def _window_centres(side: int, wrap: bool) -> np.ndarray:
    """(side,) bool: the rows (columns) a window may be centred on, all where it may wrap,
    else those whose window, offsets -HALF .. WINDOW - HALF - 1, stays inside."""
    centre = np.arange(side)
    return ((centre >= _k.HALF) & (centre <= side - _k.WINDOW + _k.HALF)) | wrap


def _search_structure(features: np.ndarray, seams: tuple[bool, bool]) -> _Axis:
    """PCA to 95% of the variance and the ANN tree of an exemplar's windows (section 4.2),
    those that do not wrap across a seam (:func:`_windows`)."""
    # Gathered in float64 and centred in place: one copy of the windows at a time.
    centred, pixels = _windows(features.astype(np.float64), seams)
    mean = centred.mean(axis=0)
    centred -= mean
    # Eigenvectors of the (64 F)^2 covariance: far cheaper than an SVD of all the windows.
    variance, vectors = np.linalg.eigh(centred.T @ centred)
    variance, vectors = np.maximum(variance[::-1], 0.0), vectors[:, ::-1]
    total = float(np.sum(variance))
    # Windows all alike (a constant exemplar) vary in no direction: one coefficient holds it.
    explained = np.cumsum(variance) / total if total > 0 else np.ones(len(variance))
    needed = int(np.searchsorted(explained, VARIANCE_KEPT)) + 1
    dims = min(needed, _k.MAX_COEFFS)
    basis = np.zeros((centred.shape[1], _k.MAX_COEFFS), np.float32)
    basis[:, :dims] = vectors[:, :dims]
    tree = kd_tree(centred @ vectors[:, :dims])
    return _Axis(features, pixels, mean.astype(np.float32), basis, dims, tree, needed,
                 float(explained[dims - 1]))


def _ann_search(ax: _Axis, query: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Approximate nearest exemplar windows of projected windows ``query`` (section 4.2),
    as the pixels they are centred on.

    Only a window closer than the current match can replace it (``keep_better_match``), so
    once every centre has a match the search is bounded by the current match's distance in
    PCA space: far fewer tree nodes are visited, and where nothing closer exists within the
    bound the current match is returned. SciPy takes one bound per call, so the queries are
    grouped by bound and each group searched with its largest.
    """
    tree = ax.tree
    if np.any(current < 0):
        return ax.window_pixels[nearest(tree, query, eps=ANN_EPS)[1]]
    bound = _distances_to_matches(tree, query, np.searchsorted(ax.window_pixels, current))
    found = current.copy()
    order = np.argsort(bound)
    for group in np.array_split(order, _BOUND_GROUPS):
        if len(group):
            _, idx = nearest(tree, query[group], eps=ANN_EPS,
                             distance_upper_bound=float(bound[group[-1]]) * (1 + 1e-6))
            hit = idx < tree.n
            found[group[hit]] = ax.window_pixels[idx[hit]]
    return found


def _distances_to_matches(tree: cKDTree, query: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Euclidean distance of each of ``query`` to the tree window in its row of ``rows``,
    taken in parts of rows: all at once, the float64 differences took about 4 bytes a voxel
    per coefficient kept, four times the coefficients' own memory. Each row's distance is its
    own, so the parts give what one pass would."""
    bound = np.empty(len(rows))
    for part in _parts(len(rows), query.shape[1]):
        bound[part] = np.linalg.norm(query[part] - tree.data[rows[part]], axis=1)
    return bound


def _parts(rows: int, width: int) -> Iterator[slice]:
    """Slices of ``rows`` rows whose ``width`` 8-byte values take ``_PART_BYTES`` each."""
    step = max(1, _PART_BYTES // (8 * max(1, width)))
    return (slice(lo, lo + step) for lo in range(0, rows, step))


class _LevelOptimizer:
    """Search and optimization phases on one level of the pyramid."""

    def __init__(self, feats: list[np.ndarray | None], seams: list[tuple[bool, bool] | None],
                 solid: wp.array, histograms: bool):
        self.solid = solid
        self.values = solid.numpy()  # a view: CPU Warp arrays share their memory
        self.n = round(solid.shape[0] ** (1 / 3))
        distinct = {id(f): (f, s) for f, s in zip(feats, seams, strict=True) if f is not None}
        structures = {k: _search_structure(f, s) for k, (f, s) in distinct.items()}
        self.axes = [None if f is None else structures[id(f)] for f in feats]
        self.constrained = wp.vec3i(*[int(a is not None) for a in self.axes])
        self.centres = self.n**3 // (GRID_SPACING * GRID_SPACING)

        sizes = [0 if f is None else f.shape[0] * f.shape[1] for f in feats]
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int)
        nfeat = solid.shape[1]
        pixels = np.concatenate([f.reshape(-1, nfeat) for f in feats if f is not None])
        self.ex = wp.array(pixels, dtype=wp.float32, device=_DEVICE)
        self.spread = float(np.sqrt(pixels.var(axis=0).sum()))
        self.ex_first = wp.vec3i(*offsets)
        self.height = wp.vec3i(*[1 if f is None else f.shape[0] for f in feats])
        self.width = wp.vec3i(*[1 if f is None else f.shape[1] for f in feats])
        self.grid_first = wp.vec3i(*[k * self.centres for k in range(3)])
        self.match = wp.full(3 * self.centres, -1, dtype=wp.int32, device=_DEVICE)
        self.weight = wp.zeros(3 * self.centres, dtype=wp.float32, device=_DEVICE)
        self.energy = wp.zeros(3 * self.centres, dtype=wp.float32, device=_DEVICE)
        self.coeffs = wp.zeros(self.centres, dtype=_k.projection, device=_DEVICE)
        self.penalty = wp.zeros(len(pixels), dtype=wp.float32, device=_DEVICE)
        self.histograms = _Histograms(pixels, feats, self.values) if histograms else None

    def search(self) -> float:
        """Search phase (section 4.2); returns the energy with the matches found."""
        n = self.n
        terms = []
        for axis, ax in enumerate(self.axes):
            if ax is None:
                continue
            mean = wp.array(ax.mean, dtype=wp.float32, device=_DEVICE)
            basis = wp.array(ax.basis, dtype=_k.projection, device=_DEVICE)
            launch_ranges(_k.project_windows, 0, self.centres,
                          [self.solid, n, axis, mean, basis, self.coeffs], device=_DEVICE)
            lo, hi = self.grid_first[axis], self.grid_first[axis] + self.centres
            found = _ann_search(ax, self.coeffs.numpy()[:, : ax.dims],
                                self.match.numpy()[lo:hi])
            found = wp.array(found, dtype=wp.int32, device=_DEVICE)
            h, w = ax.features.shape[:2]
            launch_ranges(_k.keep_better_match, 0, self.centres,
                          [self.solid, n, axis, self.ex, self.ex_first[axis], h, w, found, R,
                           MIN_DISTANCE, self.match[lo:hi], self.weight[lo:hi],
                           self.energy[lo:hi]], device=_DEVICE)
            terms.append(self.energy.numpy()[lo:hi].astype(np.float64))
        return float(np.mean(np.concatenate(terms)))

    def optimize(self, order: np.ndarray, bandwidth: float = 0.0) -> None:
        """Optimization phase (section 4.1) visiting voxels in ``order``, averaging the
        dominant mean-shift cluster of ``bandwidth`` (all texels at 0); with histogram
        matching the histograms and the penalties of equation 5 are refreshed between
        batches of that order (section 5)."""
        order_wp = wp.array(order, dtype=wp.int32, device=_DEVICE)
        refreshes = 1 if self.histograms is None else HISTOGRAM_REFRESHES
        bounds = [int(b) for b in np.linspace(0, len(order), refreshes + 1)]
        for lo, hi in pairwise(bounds):
            if self.histograms is not None:
                self.penalty.numpy()[:] = self.histograms.penalty()
                before = self.values[order[lo:hi]]
            launch_ranges(_k.optimize_voxels, lo, hi,
                          [order_wp, self.n, self.constrained, self.ex, self.ex_first,
                           self.height, self.width, self.grid_first, self.match, self.weight,
                           self.penalty, bandwidth, self.solid], device=_DEVICE)
            if self.histograms is not None:
                self.histograms.replace(before, self.values[order[lo:hi]])



class _Histograms:
    """The 16-bin per-channel histograms of section 5 and the penalties of equation 5.

    Bins span each channel's range over the level's exemplars. The exemplar histogram is the
    mean of the constrained axes' normalized histograms; the solid's is kept as counts. The
    paper leaves the histograms' scale open: excess is measured in units of an average bin
    (solid voxels / 16), so the penalty does not depend on the volume size. Tried on granite,
    this unit takes the histogram distance of a 32^3 solid from 1.03 to 0.43; ten times
    larger goes to 0.30 but raises the neighbourhood energy.
    """

    def __init__(self, pixels: np.ndarray, feats: list[np.ndarray | None], values: np.ndarray):
        self.lo = pixels.min(axis=0)
        self.scale = BINS / np.maximum(pixels.max(axis=0) - self.lo, 1e-12)
        self.voxels = len(values)
        given = [f.reshape(-1, f.shape[2]) for f in feats if f is not None]
        self.target = np.mean([self._counts(g) / len(g) for g in given], axis=0)
        self.channel = np.arange(pixels.shape[1])
        self.pixel_bins = self._bins(pixels)
        self.counts = self._counts(values)

    def _bins(self, values: np.ndarray) -> np.ndarray:
        return np.clip(((values - self.lo) * self.scale).astype(np.int64), 0, BINS - 1)

    def _counts(self, values: np.ndarray) -> np.ndarray:
        """(F, 16) counts of the values' bins per channel, taken in parts of the values: a
        whole level's int64 bin indices took 16 bytes a voxel per channel, for 8 channels
        more than the search's coefficients."""
        channels = values.shape[1]
        counts = np.zeros(channels * BINS, np.int64)
        for part in _parts(len(values), channels):
            bins = self._bins(values[part]) + np.arange(channels) * BINS
            counts += np.bincount(bins.ravel(), minlength=channels * BINS)
        return counts.reshape(-1, BINS)

    def replace(self, before: np.ndarray, after: np.ndarray) -> None:
        """Account for voxels that changed from ``before`` to ``after``."""
        self.counts += self._counts(after) - self._counts(before)

    def penalty(self) -> np.ndarray:
        """Per exemplar pixel, the sum over channels of its bins' excess (equation 5)."""
        excess = np.maximum(0.0, self.counts / self.voxels - self.target) * BINS
        return excess[self.channel, self.pixel_bins].sum(axis=1).astype(np.float32)
