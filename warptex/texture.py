"""Point queries on a lazily synthesized solid texture (Dong 2008, section 5.2).

Colors at arbitrary 3D points are synthesized on first touch and kept in a
:class:`~warptex.store.BrickStore`, so the cost follows what is looked at. Texture space:
one unit is one finest voxel; voxel v occupies [v, v + 1)^3 and its center is v + 0.5.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable, Sequence
from numbers import Integral
from pathlib import Path
from typing import Any, NoReturn, Protocol

import numpy as np
import warp as wp

from kernels.lookup import BRICK_VOXELS
from warptex.archive import file_problem
from warptex.candidate_set import CandidateSet
from warptex.candidates import precompute
from warptex.exemplar import Exemplar, axis_exemplars, srgb_encoded
from warptex.machine import memory_problem
from warptex.settings import (
    DEFAULT_CACHE_BYTES,
    DEFAULT_JITTER,
    DEFAULT_PASSES,
    FILTERS,
    Filter,
    check_file_name,
    check_flag,
    check_settings,
    names_folder,
)
from warptex.store import (
    BATCH_VOXELS,
    POINT_LIMIT,
    BrickStore,
    check_lookup_channels,
    check_store_settings,
)
from warptex.store_files import StoreFileError, check_store_path, settings_differences
from warptex.synthesis import (
    REQUEST_BYTES_PER_VOXEL,
    Synthesizer,
    engine_device,
    not_pickled,
)
from warptex.thread_warnings import given_again, warn

BATCH = 1 << 20  # points per batch of a query: bounds the memory of one lookup and synthesis
_SLAB = 1 << 16  # points per query of query_slabs: small enough for its bar to move
# Beyond it, a renderer's points are moved by whole periods of this many voxels (wrap_far).
FAR_PERIOD = 1 << 22


def wrap_far(c: Any, select: Callable = np.where, rint: Callable = np.rint) -> Any:
    """Texture coordinates ``c`` as a renderer reads them: unchanged strictly within
    +-POINT_LIMIT, else moved by whole periods of FAR_PERIOD voxels to within FAR_PERIOD / 2
    of the origin, so that every finite shading point has a color (the texture repeats only
    that far out). Exact in float64 at any magnitude, as the period is a power of two; NaN
    and infinity come out NaN, quietly (Python's ``round`` raises on them). ``select`` and
    ``rint`` (ties to even) are NumPy's by default: Dr.Jit's and Python's give the same
    bits."""
    if isinstance(c, list | tuple):  # points as a script writes them
        c = np.asarray(c, np.float64)
    if not isinstance(c, np.ndarray | np.generic):
        # Python floats, per coordinate of each shading point of the scalar variants, or
        # Dr.Jit arrays: no NumPy warning to mute, which would cost 5x the work.
        return _moved_by_periods(c, select, rint)
    with np.errstate(invalid="ignore"):  # infinity minus infinity
        return _moved_by_periods(c, select, rint)


def _moved_by_periods(c: Any, select: Callable, rint: Callable) -> Any:
    return select(abs(c) < POINT_LIMIT, c, c - FAR_PERIOD * rint(c / FAR_PERIOD))


# Textures of this process that have a store file, so that two of other settings are not
# given the same one: each would start empty from the other's file and replace it on saving.
# Mitsuba builds a scene's plugins on several threads, so checking and joining are one step.
_WITH_STORE_FILES: weakref.WeakSet[SolidTexture] = weakref.WeakSet()
_STORE_FILES_LOCK = threading.Lock()


def _check_unshared(path: Path, synthesizer: Synthesizer,
                    joining: SolidTexture | None = None) -> None:
    """Raise StoreFileError if a live texture of other settings has ``path`` as its store
    file; else let ``joining``, if given, join them. Textures of the same settings may
    share one, as their voxels are the same (each save merges with the file)."""
    where = path.resolve()
    with _STORE_FILES_LOCK:
        for other in list(_WITH_STORE_FILES):
            if other.path is not None and other.path.resolve() == where:
                differences = settings_differences(other.synthesizer, synthesizer)
                if differences:
                    raise StoreFileError(
                        f"{path}: already the brick store file of another texture of this "
                        f"process ({differences}); each would discard the other's bricks, so "
                        "give each texture its own file")
        if joining is not None:
            _WITH_STORE_FILES.add(joining)


def _store_file(store: object, name: str = "store") -> Path:
    """The ``store`` file (the argument ``name``), refused before any work (StoreFileError)
    where it names a folder, holds a file of another kind, or does not exist and could not
    be written: its first save would fail after the work it was to keep."""
    path = check_file_name(name, store)
    if isinstance(store, str) and names_folder(store):
        raise StoreFileError(f"{name} names a folder, not a file: {store!r}")
    check_store_path(path)
    problem = None if path.exists() else file_problem(path)
    if problem is not None:
        raise StoreFileError(f"{path}: a brick store could not be saved there: {problem}")
    return path


class SolidTexture:
    """An unbounded solid texture synthesized from exemplar photos, queried at points.

    ``source`` is an exemplar path, an :class:`Exemplar` or a :class:`CandidateSet`
    (pre-computation is cached on disk); ``ey`` and ``ez`` the exemplars of the y and z axes
    where they differ from x's (as ``precompute`` takes them: y's defaults to x's, z's to
    y's; encoded alike, as a voxel's color averages theirs). ``seed`` (0 to 2^31 - 1) picks
    one of the texture's many solids; ``jitter`` (0 to 64) is the strength of the random
    warp that varies the initial tiling (Dong 2008, 5.1), through which the seed acts, and
    through ``shifted_tiles``: at jitter 0 without them every seed gives the same solid.
    ``store`` names a brick store file: loaded when it exists and matches this texture,
    written by :meth:`save`; a missing one that could not be written where it is named, or
    one that a live texture of other settings has, is refused (StoreFileError). An existing
    one in a folder this process cannot write serves as a read-only warm start: :meth:`save`
    fails only where voxels were synthesized since. ``cache_bytes`` bounds the bricks kept
    in memory. ``passes`` is the number of correction passes per level (Dong 2008, 5.1):
    more look better and cost more (see BENCHMARKS.md). ``shifted_tiles`` shifts each tile
    of the initial tiling by its own offset (:class:`Synthesizer`).
    ``whole_bricks=False`` synthesizes only the voxels queries read instead of their whole
    8^3 bricks: faster for thin sets such as mesh surfaces and cuts (see
    :class:`~warptex.store.BrickStore`). ``device`` is the Warp device that synthesizes
    (default: a GPU when there is one, see :func:`warptex.device`).

    Colors come as the exemplars store them; ``srgb`` says whether that is sRGB-encoded
    (8-bit photos) or linear, None where a CandidateSet was given, which does not record it.
    ``synthesizer`` is the :class:`Synthesizer` behind the store, for voxels by integer
    coordinates (``synthesizer.voxels``, ``synthesizer.box``).
    """

    def __init__(
        self,
        source: str | Path | Exemplar | CandidateSet,
        *,
        ey: str | Path | Exemplar | None = None,
        ez: str | Path | Exemplar | None = None,
        seed: int = 0,
        jitter: float = DEFAULT_JITTER,
        device: str | None = None,
        cache_bytes: int = DEFAULT_CACHE_BYTES,
        store: str | Path | None = None,
        passes: int = DEFAULT_PASSES,
        whole_bricks: bool = True,
        shifted_tiles: bool = False,
    ) -> None:
        # Everything refusable is refused before pre-computing, which takes minutes for a
        # large exemplar.
        # Absolute: a later change of the working folder does not move where it is saved.
        self.path = None if store is None else _store_file(store).absolute()
        check_settings(jitter, passes, seed)
        check_flag("shifted_tiles", shifted_tiles)
        check_store_settings(cache_bytes, whole_bricks)
        device = engine_device(device)
        # The exemplars', their candidates' (a damaged cache) and the engine's (the seed's)
        # warnings at the line that made the texture.
        with given_again(2):
            if isinstance(source, CandidateSet):
                if ey is not None or ez is not None:
                    raise TypeError("ey and ez name exemplars of the y and z axes; a "
                                    "CandidateSet holds those of its three axes already")
                candidates, self.srgb = source, None
            else:
                exemplars = axis_exemplars(source, ey, ez)
                check_lookup_channels(exemplars[0].channels)
                self.srgb = srgb_encoded(exemplars, raw=None)
                candidates = precompute(*exemplars, progress=None)
            self.synthesizer = Synthesizer(candidates, seed, jitter, device=device,
                                           passes=passes, shifted_tiles=shifted_tiles)
        if self.path is not None:
            _check_unshared(self.path, self.synthesizer, joining=self)
        try:
            if self.path is not None and self.path.exists():
                with given_again(2):  # at the line that made the texture, not this one
                    self.store = BrickStore.load(self.path, self.synthesizer,
                                                 cache_bytes=cache_bytes,
                                                 whole_bricks=whole_bricks)
            else:
                self.store = BrickStore(self.synthesizer, cache_bytes=cache_bytes,
                                        whole_bricks=whole_bricks)
        except BaseException:
            with _STORE_FILES_LOCK:  # another thread may be going through the set
                _WITH_STORE_FILES.discard(self)  # no store file of its own after all
            raise

    @property
    def channels(self) -> int:
        """Channels of the colors a query gives: the exemplars' (3 for RGB)."""
        return self.store.channels

    def __getstate__(self) -> NoReturn:
        raise TypeError(not_pickled("a SolidTexture"))

    def query(
        self,
        points: np.ndarray | wp.array,
        filter: Filter = "trilinear",
        fill: float | Sequence[float] | None = None,
    ) -> np.ndarray:
        """Colors (N, C) float32 at ``points`` (N, 3) float32 or float64, in texture space:
        one unit is one finest voxel, and voxel v's center is v + 0.5 (so ``nearest`` at
        ``v + 0.5`` is ``synthesizer.voxels(v)``). Colors are as the exemplar stores them
        (``srgb``).

        ``nearest`` is the color of the voxel containing the point, ``trilinear`` the
        blend of the 8 voxel centers around it. Points that are NaN or infinite, or masked
        in a NumPy masked array, raise ValueError unless ``fill`` gives their color.
        """
        pts = _as_points(points)
        _check_filter(filter)
        fill_color = None if fill is None else self._fill_color(fill)
        finite = np.isfinite(pts).all(axis=1)
        if fill_color is None and not finite.all():
            raise ValueError(f"{int((~finite).sum())} of {len(pts)} points are NaN, "
                             "infinite or masked; pass fill= to give them a color instead")
        # Refused before any batch is synthesized: a far point late in a large query would
        # otherwise be found after minutes of work.
        far = finite & (np.abs(pts) >= POINT_LIMIT).any(axis=1)
        if far.any():
            raise ValueError(f"{int(far.sum())} of {len(pts)} points lie at or beyond "
                             f"+-{POINT_LIMIT} voxels; points must lie strictly within it")
        out = np.empty((len(pts), self.channels), np.float32)
        for start in range(0, len(pts), BATCH):
            chunk = pts[start : start + BATCH]
            dest = out[start : start + BATCH]
            good = np.isfinite(chunk).all(axis=1) if fill_color is not None else None
            if good is not None and not good.all():
                dest[~good] = fill_color
                colors = np.empty((int(good.sum()), self.channels), np.float32)
                self._sample(chunk[good], filter, colors)
                dest[good] = colors
            else:
                self._sample(chunk, filter, dest)
        return out

    def slice(
        self,
        origin: Sequence[float],
        u: Sequence[float],
        v: Sequence[float],
        shape: tuple[int, int],
        filter: Filter = "trilinear",
    ) -> np.ndarray:
        """Colors (H, W, C) on any plane (Dong 2008, 6.4): pixel (r, c) shows the point
        ``origin + r*u + c*v``; the plane need not be axis-aligned (``u`` and ``v`` zero or
        parallel are warned of: a line, not a plane)."""
        _check_filter(filter)  # before the plane's points are made, which may take seconds
        for name, vector in (("origin", origin), ("u", u), ("v", v)):
            a = np.asarray(vector)
            real = np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)
            if a.shape != (3,) or not real or not np.isfinite(a).all():
                raise ValueError(f"{name} must be three finite real numbers, got {vector!r}")
        rows_cols = tuple(shape) if np.ndim(shape) == 1 else ()
        if len(rows_cols) != 2 or not all(isinstance(n, Integral) and not isinstance(n, bool)
                                          and n > 0 for n in rows_cols):
            raise ValueError(f"shape must be two positive ints (rows, columns), got {shape!r}")
        # Its points (float64, and their grid while made) and colors, and one query batch's
        # request arrays: the voxels its points read (a whole brick each where the store
        # keeps whole bricks), at most the store's BATCH_VOXELS at a time.
        count = int(rows_cols[0]) * int(rows_cols[1])  # NumPy integers would wrap around
        per_point = ((8 if filter == "trilinear" else 1)
                     * (BRICK_VOXELS if self.store.whole_bricks else 1))
        batch = min(count * per_point, BATCH_VOXELS)
        need = count * (40 + 4 * self.channels) + batch * REQUEST_BYTES_PER_VOXEL
        problem = memory_problem(need)
        if problem is not None:
            raise ValueError(f"a slice of shape {tuple(shape)} {problem}; take it in parts")
        if not plane_within_limit(origin, u, v, rows_cols):  # before its minutes of work
            raise ValueError(f"the plane reaches beyond the texture's coordinate range "
                             f"(+-{POINT_LIMIT} voxels): check origin, u, v and shape")
        warn_unless_a_plane(u, v, "u and v", stacklevel=3)
        points = plane_points(origin, u, v, rows_cols)
        return self.query(points, filter=filter).reshape(shape[0], shape[1], self.channels)

    def save(self, path: str | Path | None = None) -> Path:
        """Write the brick store to ``path`` or to the ``store`` path given at creation,
        and return that file, which then holds the store's voxels (:meth:`BrickStore.save`
        does not rewrite a file that holds them already), making its folder if missing, as
        the commands' ``-o`` do; the store file of a live texture of other settings is
        refused (StoreFileError)."""
        target = _store_file(path, "path") if path is not None else self.path
        if target is None:
            raise ValueError("no store path: pass one here or as SolidTexture(store=...)")
        _check_unshared(target, self.synthesizer)
        with given_again(2):  # at the caller's line, not this one
            self.store.save(target)
        return target

    def _sample(self, points: np.ndarray, filter: str, out: np.ndarray) -> None:
        self.store.sample(np.ascontiguousarray(points, np.float64), filter, out)

    def _fill_color(self, fill: float | Sequence[float]) -> np.ndarray:
        try:
            given = np.asarray(fill)
        except (TypeError, ValueError):  # ragged lists
            given = np.asarray(None)
        # Numbers only (np.float32 reads True as 1 and "0.25" as 0.25); the rest is refused
        # below, in words of its own.
        color = (given.astype(np.float32) if given.dtype.kind in "iuf"
                 else np.full(1, np.nan, np.float32))
        if color.shape not in ((), (self.channels,)) or not np.isfinite(color).all():
            raise ValueError(f"fill must be one finite value or {self.channels} of them, "
                             f"got {fill!r}")
        return np.broadcast_to(color, (self.channels,))


def plane_points(origin: Sequence[float], u: Sequence[float], v: Sequence[float],
                 shape: tuple[int, int]) -> np.ndarray:
    """Points (H*W, 3) of a planar grid: pixel (r, c) lies at origin + r*u + c*v. In float64,
    as far from the origin float32 would move them by up to half a voxel."""
    h, w = shape
    r, c = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    origin, u, v = (np.asarray(a, np.float64) for a in (origin, u, v))
    return origin + r.reshape(-1, 1) * u + c.reshape(-1, 1) * v


def plane_within_limit(origin: Sequence[float], u: Sequence[float], v: Sequence[float],
                       shape: tuple[int, int]) -> bool:
    """Whether every pixel of :func:`plane_points`' grid lies strictly within +-POINT_LIMIT,
    as a query's points must: its corners are its extremes. Finite vectors may still
    overflow there, and are then not within."""
    h, w = shape
    origin, u, v = (np.asarray(a, np.float64) for a in (origin, u, v))
    with np.errstate(over="ignore", invalid="ignore"):
        corners = np.array([origin + r * u + c * v for r in (0, h - 1) for c in (0, w - 1)])
        return bool((np.abs(corners) < POINT_LIMIT).all())


def warn_unless_a_plane(u: Sequence[float], v: Sequence[float], names: str,
                        stacklevel: int = 2) -> None:
    """Warn where ``u`` and ``v`` (called ``names``) are zero or parallel: their slice shows
    one line or one point, a mistake more often than a wish."""
    if not np.cross(np.asarray(u, np.float64), np.asarray(v, np.float64)).any():
        warn(f"{names} are zero or parallel: the slice shows a line or a point, not a plane",
             stacklevel=stacklevel)


def _as_points(points: np.ndarray | wp.array) -> np.ndarray:
    """(N, 3) float32 or float64 host array of ``points``, or a clear error. A masked
    array's masked points become NaN: np.asarray would read the values under the mask."""
    if isinstance(points, wp.array):
        points = points.numpy()
    masked = np.ma.isMaskedArray(points)
    points = np.ma.asarray(points) if masked else np.asarray(points)
    if points.dtype.kind != "f" or points.dtype.itemsize not in (4, 8):
        raise TypeError(f"points must be float32 or float64, got {points.dtype}")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    if masked:
        points = np.where(np.ma.getmaskarray(points).any(axis=1, keepdims=True), np.nan,
                          points.data)
    return points


class PointTexture(Protocol):
    """Anything with a :meth:`SolidTexture.query` and its ``channels``: a texture, or a
    stand-in in tests."""

    @property
    def channels(self) -> int: ...

    def query(self, points: np.ndarray, filter: Filter = ...) -> np.ndarray: ...


def _check_filter(filter: object) -> None:
    if filter not in FILTERS:
        raise ValueError(f"filter must be one of {FILTERS}, got {filter!r}")


def query_slabs(texture: PointTexture, points: np.ndarray, filter: Filter = "trilinear",
                progress: str | None = None) -> np.ndarray:
    """``texture.query(points, filter)`` in slabs along x, under a progress bar named
    ``progress`` (none if None): the same colours as one query, as every point's color
    is its own. Points are taken in order of x, so the slabs' dependencies overlap only at
    their faces."""
    from tqdm.auto import tqdm

    points = _as_points(points)  # a masked point is NaN, as query() refuses it
    order = np.argsort(points[:, 0], kind="stable")
    out = np.empty((len(points), texture.channels), np.float32)
    # Shown for one slab too: a cut's vertices are one, and synthesizing what they read at a
    # fine resolution takes minutes; the bar names the step meanwhile.
    with tqdm(total=len(points), desc=progress, unit="point", unit_scale=True,
              disable=progress is None) as bar:
        for first in range(0, len(points), _SLAB):
            part = order[first : first + _SLAB]
            out[part] = texture.query(points[part], filter=filter)
            bar.update(len(part))
    return out
