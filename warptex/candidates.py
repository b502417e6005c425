"""3D candidate pre-computation (Dong 2008, section 4; 5.1 "Separation of the first
candidate coordinate"; 6.1-6.2).

In every pixel of every pyramid level of each exemplar we keep a short list of coordinate
triples whose three interleaved N x N neighbourhoods agree along their crossbar (4.1) and
form coherent patches with the candidates of neighbouring pixels (4.2), plus the usual 2D
k-coherent candidates for the first step of the two-step search (5.1).

Orientation is cyclic: the exemplar of axis k spans volume axes (k+1, k+2) as its (first,
second) pixel coordinates. Rotating the volume x -> y -> z -> x then maps the three roles
onto each other, so one exemplar repeated thrice needs a single candidate structure.
"""

from __future__ import annotations

import functools
import hashlib
import itertools
import json
import os
import sys
from collections.abc import Callable, Sequence
from functools import cache
from pathlib import Path

import numpy as np
import warp as wp
from tqdm.auto import tqdm

from kernels import candidates as _k
from kernels import common as _common
from kernels.synthesis import BASIS_LIMIT, MAX_DIMS, PROJ_LIMIT
from warptex import candidate_set, exact_pca, parallel, warp_runtime
from warptex.archive import folder_problem
from warptex.candidate_set import (
    FORMAT_VERSION,
    MIN_SPLIT_PIXELS,
    PRECOMPUTE_DEVICE,
    CandidateCacheError,
    CandidateParams,
    CandidateSet,
    RoleLevel,
    SourceLevel,
    candidate_meta,
    check_feature_channels,
    laid_out,
    pixel_strips,
    read_candidate_arrays,
    resolved_params,
    role_strips,
    role_trio,
    usable_pixels,
    with_crossbar_errors,
)
from warptex.code_digest import code_digest, module_sources
from warptex.exemplar import (
    Exemplar,
    ExemplarError,
    axis_exemplars,
    check_same_channels,
    wrapping_edges,
)
from warptex.float_env import ieee_arithmetic
from warptex.machine import memory_problem
from warptex.parallel import launch_ranges
from warptex.settings import (
    check_flag,
)
from warptex.thread_warnings import given_again, warn
from warptex.warp_runtime import init_warp

PROJ_BITS = PROJ_LIMIT.bit_length()  # projections quantized to signed PROJ_BITS + 1 bits
CACHE_PREFIX, CACHE_SUFFIX = "candidates-", ".wtc"
_MARK_BYTES = 16 << 20  # scratch bitmaps of the coherence test
# A nearest-rows search holds at most so many retrieved rows at once, and so many terms of
# their distances (int64), however widely ties make it search.
_NEAREST_ENTRIES = 1 << 22
_DISTANCE_TERMS = 1 << 21
# Peak memory of a pre-computation at the default parameters: a base and so much per pixel
# of its largest exemplar, more where the axes have exemplars of their own; above every peak
# measured (BENCHMARKS.md, "Large exemplars"). Larger exemplars than LARGE_PIXELS take
# minutes, and are warned of.
_BASE_BYTES = 256 << 20
_BYTES_PER_PIXEL = 14 << 10
_BYTES_PER_PIXEL_PER_SOURCE = 2 << 10  # for each exemplar beyond the first
# For each feature channel beyond RGB's three: a 32-channel exemplar of 64^2 peaked at 372 MiB
# where 312 were counted, of 96^2 at 445 (a review's measure, 2026-12-07).
_BYTES_PER_EXTRA_CHANNEL = 4 << 20
LARGE_PIXELS = 256 * 256
_SHRINK_ADVICE = ("shrink it when loading: max_size=256 in Exemplar.load, --exemplar-max-size "
                  '256 on the command line, <integer name="exemplar_max_size" value="256"/> in '
                  "a scene")


@ieee_arithmetic()  # the same candidates on a renderer's thread (float_env)
def precompute(
    ex: Exemplar | str | Path,
    ey: Exemplar | str | Path | None = None,
    ez: Exemplar | str | Path | None = None,
    *,
    cache: bool = True,
    progress: bool | None = False,
    **params: object,
) -> CandidateSet:
    """Pre-compute the 3D candidates of three exemplars (Dong 2008, section 4).

    ``ey`` defaults to ``ex`` and ``ez`` to ``ey`` (:func:`~warptex.exemplar.axis_triple`,
    as the commands' --ey/--ez and the plugin's ``exemplar_y``/``_z``). With ``cache`` the
    result is stored under ``WARPTEX_CACHE`` keyed by exemplar content and parameters, and
    a later call loads it; a damaged cache file, or one that holds the candidates of other
    exemplars or parameters (copied or renamed), is reported once and recomputed, and a
    cache that cannot be written is reported once and left out. ``progress`` shows a bar on
    stderr; None shows it when stderr is a terminal. ``params`` override
    :data:`~warptex.candidate_set.DEFAULT_PARAMS` by name (``neighborhood``, ``strips``,
    ``keep``, ``candidates_3d``, ``candidates_2d``, ``candidates_2d_finest``, ``variance``,
    ``min_dims``, ``max_dims``, ``coherence_rounds``, ``tileable``).

    Raises:
        ExemplarError: an exemplar that cannot be read or used, the axes' exemplars of
            different channels, or a pre-computation this machine's memory cannot hold.
        TypeError: a parameter unknown or of the wrong type.
        ValueError: a parameter out of its range.
    """
    check_flag("cache", cache)
    if progress is not None:
        check_flag("progress", progress)
    # An exemplar's warnings at the line that called this, above ieee_arithmetic's wrapper.
    with given_again(3):
        exemplars = axis_exemplars(ex, ey, ez)
    check_same_channels(exemplars)
    p = resolved_params(params)
    try:  # before the cache folder is looked at, as for any exemplar that cannot be used
        check_feature_channels(exemplars[0].features.shape[2], p["neighborhood"])
    except ValueError as error:
        raise ExemplarError(f"{exemplars[0].path or exemplars[0].name}: {error}") from None
    path = cache_path(exemplars, p) if cache else None
    if path is not None and cache_file_there(path):
        try:
            loaded = _cached(path, exemplars, p)
            loaded.cache_status = "loaded"
            return loaded
        except CandidateCacheError as e:
            if cache_file_there(path):  # else pruned meanwhile (`warptex cache`): no damage
                warn(f"ignoring damaged candidate cache, recomputing: {e}", stacklevel=2)
    _check_size(exemplars)
    result = _compute(exemplars, p, progress)
    if path is not None:
        try:
            result._write(path)
            result.cache_status = "written"
        except OSError as e:
            result.cache_status = "not written"
            # Why the folder takes no file (a file in its place, say) says more than errno.
            problem = folder_problem(path.parent)
            why = (f"{path.parent}: {problem}" if problem is not None
                   else f"cannot write {path} ({e.strerror or e})")
            warn(f"candidates not cached: {why}; WARPTEX_CACHE sets the cache folder",
                 stacklevel=2)
    return result


def _cached(path: Path, exemplars: list[Exemplar], params: CandidateParams) -> CandidateSet:
    """The candidates cached at ``path``, if they are those of ``exemplars`` and ``params``."""
    return with_crossbar_errors(_cached_set(path, exemplars, params))


def _cached_set(path: Path, exemplars: list[Exemplar], params: CandidateParams) -> CandidateSet:
    """The candidates of the cache file ``path`` (crossbar errors not yet derived), whole
    (checksummed), laid out as the kernels index them, and of ``exemplars`` and
    ``params``; CandidateCacheError otherwise."""
    arrays = read_candidate_arrays(path)
    meta = candidate_meta(arrays, path)
    found = {"digests": meta["digests"], "params": meta["params"]}
    # Through JSON, as the file's went: tuples become lists, so equal compares equal.
    wanted = json.loads(json.dumps({"digests": [e.digest() for e in exemplars], "params": params}))
    if wanted != found:
        raise CandidateCacheError(f"{path}: holds the candidates of other exemplars or "
                                  "parameters (a copied or renamed cache file)")
    if not computed_here(meta):
        raise CandidateCacheError(f"{path}: holds candidates another version of warptex "
                                  "computed (a copied or renamed cache file)")
    return laid_out(arrays, path)


def precompute_bytes(exemplars: Sequence[Exemplar]) -> int:
    """About the peak memory of pre-computing the candidates of the exemplars of the three
    axes (or one for all) at the default parameters: the largest decides, and each distinct
    exemplar adds some (BENCHMARKS.md, "Large exemplars")."""
    pixels = max(e.shape[0] * e.shape[1] for e in exemplars)
    sources = len({e.digest() for e in exemplars})
    per_pixel = _BYTES_PER_PIXEL + (sources - 1) * _BYTES_PER_PIXEL_PER_SOURCE
    extra_channels = max(exemplars[0].features.shape[2] - 3, 0)
    return _BASE_BYTES + extra_channels * _BYTES_PER_EXTRA_CHANNEL + pixels * per_pixel


def _check_size(exemplars: list[Exemplar]) -> None:
    """Refuse, before any work, exemplars whose pre-computation would not fit in this
    machine's memory, and warn of those that take minutes (a photograph as it comes)."""
    largest = max(exemplars, key=lambda e: e.shape[0] * e.shape[1])
    h, w = largest.shape
    what = f"{largest.path or largest.name}: {w}x{h} pixels"
    problem = memory_problem(precompute_bytes(exemplars))
    if problem is not None:
        raise ExemplarError(f"{what}; pre-computing its candidates {problem}; {_SHRINK_ADVICE}")
    if h * w > LARGE_PIXELS:
        warn(f"{what}, a large exemplar: pre-computing its candidates takes minutes "
             "to hours (5 minutes at 512x512 on 2 CPU cores), once, as they are "
             f"cached; to {_SHRINK_ADVICE}", stacklevel=3)


def cache_dir() -> Path:
    """Folder of the on-disk caches: ``WARPTEX_CACHE`` or the user's cache directory."""
    env = os.environ.get("WARPTEX_CACHE")
    if env:  # "~/..." as a shell would take it; absolute, so that listings say where
        return Path(env).expanduser().absolute()
    base = Path(os.environ.get("XDG_CACHE_HOME") or "")
    # The XDG specification ignores a relative path: it would move with the working folder.
    return (base if base.is_absolute() else Path.home() / ".cache") / "warptex"


def cache_path(exemplars: list[Exemplar], params: CandidateParams) -> Path:
    """Where the candidates of ``exemplars`` (x, y, z) and ``params`` are cached."""
    return cache_dir() / cache_file_name([e.digest() for e in exemplars], params)


def cache_file_there(path: Path) -> bool:
    """Whether something is at the cache file ``path``; False where it cannot be looked up
    (``WARPTEX_CACHE`` under a folder this user may not search, a name too long), which
    writing it then reports, as for any cache that cannot be written."""
    try:
        return path.exists()
    except OSError:
        return False


def cache_file_name(digests: Sequence[str], params: CandidateParams) -> str:
    """The name this warptex gives the cache file of exemplars of these content digests
    (x, y, z) and parameters; a file under another name is never read by it."""
    key = json.dumps(
        {"v": FORMAT_VERSION, "params": params, "digests": list(digests),
         "code": _code_digest()},
        sort_keys=True,
    )
    return f"{CACHE_PREFIX}{hashlib.sha256(key.encode()).hexdigest()[:40]}{CACHE_SUFFIX}"


@cache
def _code_digest() -> str:
    """Digest of the code that decides the candidates (``warptex.code_digest``)."""
    return code_digest(_deciding_sources(), f"{MAX_DIMS} {PROJ_LIMIT} {BASIS_LIMIT}")


def _deciding_sources() -> list[Path] | None:
    """This module, the candidate set's (the crossbar errors derived on loading a file),
    its kernels and their building blocks, how they are launched (ranges of a launch split
    over threads), its PCA and the exemplar's pyramid; None where a module has no source
    file."""
    return module_sources((sys.modules[__name__], candidate_set, _k, _common, parallel,
                           warp_runtime, exact_pca, sys.modules[Exemplar.__module__]))


def computed_here(meta: dict) -> bool:
    """Whether a candidate file's ``meta`` says this code computed it: a cache file renamed
    from another version's name holds what other code computed."""
    return meta.get("code") == _code_digest()


_code_digest()  # now: the code this process runs, even if its files are edited meanwhile


def cached_candidate_path(ex: Exemplar, tileable: bool | str = "auto") -> Path | None:
    """The cache file of ``ex`` repeated thrice with default parameters but ``tileable``,
    if it is there, whole (checksummed) and of these exemplars and parameters; None for a
    damaged one."""
    exemplars, params = [ex, ex, ex], resolved_params({"tileable": tileable})
    path = cache_path(exemplars, params)
    if not cache_file_there(path):
        return None
    try:
        _cached_set(path, exemplars, params)
    except CandidateCacheError:
        return None
    return path


def _compute(exemplars: list[Exemplar], p: dict, progress: bool | None) -> CandidateSet:
    init_warp()
    digests = tuple(e.digest() for e in exemplars)
    unique = list(dict.fromkeys(digests))
    axis_source = tuple(unique.index(d) for d in digests)
    srcs = [exemplars[digests.index(d)] for d in unique]
    # Candidates keep away from the seams and the pyramid does not blur across them.
    seam_edges = [s.seams(p["tileable"]) for s in srcs]
    pyramids = [s.pyramid(seams=seams) for s, seams in zip(srcs, seam_edges, strict=True)]
    num_levels = min(len(pyr) for pyr in pyramids)
    # Align pyramids at their finest level when exemplars differ in size.
    pyramids = [pyr[len(pyr) - num_levels :] for pyr in pyramids]
    lo, hi = _feature_range(srcs)
    shared = len(unique) == 1
    roles_per_level = 1 if shared else 3
    sources: list[list[SourceLevel]] = []
    roles: list[list[RoleLevel]] = []
    fallbacks: list[int] = []
    # Work grows with the pixels of a level (the finest holds three quarters of them), so
    # the bar counts pixels rather than steps.
    pixels = [max(pyr[level].shape[0] * pyr[level].shape[1] for pyr in pyramids)
              for level in range(num_levels)]
    bar = tqdm(
        total=sum(pixels) * (len(srcs) + roles_per_level),
        desc="candidates",
        disable=None if progress is None else not progress,
        unit="px",
        unit_scale=True,
    )
    for level in range(num_levels):
        k2 = int(p["candidates_2d_finest" if level == num_levels - 1 else "candidates_2d"])
        k3 = int(p["candidates_3d"])
        lvl_sources = []
        for pyr, seams in zip(pyramids, seam_edges, strict=True):
            feat = _quantize(pyr[level].features, lo, hi)
            margins = _margins(feat.shape[:2], seams, int(p["neighborhood"]))
            lvl_sources.append(_source_level(feat, p, k2, margins))
            bar.update(pixels[level])
        lvl_roles = []
        for role in range(roles_per_level):
            # Half after the crossbar search, half after the coherence test: each takes
            # about half of a role's time (24 s at a 256 px finest level).
            lvl_roles.append(_role_level(role_trio(lvl_sources, axis_source, role), p, k3,
                                         functools.partial(bar.update, pixels[level] / 2)))
        sources.append(lvl_sources)
        roles.append(lvl_roles)
        fallbacks.append(int(sum(r.fallback.sum() for r in lvl_roles)))
    bar.close()
    cs = CandidateSet(
        params=dict(p),
        digests=digests,
        axis_source=axis_source,
        colors=[pyr[-1].colors.astype(np.float32) for pyr in pyramids],
        sources=sources,
        roles=roles,
        names=tuple(_exemplar_label(e) for e in exemplars),
        code=_code_digest(),
    )
    cs.stats = {"fallback_pixels": fallbacks}
    return cs


def _exemplar_label(ex: Exemplar) -> str:
    """``ex``'s name, with what sets it apart from its file as loaded plainly (its size
    where shrunk, channels other than RGB, a feature-distance channel): what cache listings
    name it by."""
    h, w = ex.shape
    notes = [f"shrunk to {w}x{h}"] if ex.file_shape not in (None, ex.shape) else []
    if ex.channels != 3:  # an alpha channel kept, or a grey photo
        notes.append(f"{ex.channels} channel{'s' if ex.channels > 1 else ''}")
    if ex.features_from is not None:  # set exactly where there is a feature channel
        notes.append({"given": "feature distance", "automatic": "automatic feature distance"}
                     .get(ex.features_from, f"feature distance from {ex.features_from}"))
    return f"{ex.name} ({', '.join(notes)})" if notes else str(ex.name)


def _feature_range(srcs: list[Exemplar]) -> tuple[np.ndarray, np.ndarray]:
    """The range features are quantized over, the same for all exemplars so that their
    quantized features compare: one for all color channels, so that every distance is
    section 5.2's "L2 norm on color differences" (a range per channel weighted each by its
    inverse square: wood_rosewood's blue 13 times its red), and one of its own for a
    feature-distance channel, which is no color."""
    stacked = np.concatenate([s.features.reshape(-1, s.features.shape[2]) for s in srcs])
    lo = stacked.min(axis=0).astype(np.float64)
    hi = stacked.max(axis=0).astype(np.float64)
    colors = srcs[0].channels
    lo[:colors], hi[:colors] = lo[:colors].min(), hi[:colors].max()
    return lo, np.where(hi > lo, hi, lo + 1.0)


def _margins(size: tuple[int, int], seams: tuple[bool, bool], n: int) -> tuple[int, int]:
    """Rows and columns kept from the edges that form a seam: N // 2, so that no N x N
    neighbourhood of a candidate wraps across them. A level too small to keep N rows or
    columns inside wraps as the paper's exemplars do; the finer levels correct it."""
    return tuple(0 if wrap else n // 2 for wrap in wrapping_edges(seams, size, n))


def _quantize(features: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    q = np.rint((features.astype(np.float64) - lo) / (hi - lo) * 255.0)
    return np.clip(q, 0, 255).astype(np.uint8)


def _neighborhoods(feat: np.ndarray, n: int) -> np.ndarray:
    """Toroidal N x N neighbourhood vectors, (h*w, N*N*F) int64, in (a, b, channel) order.

    ``a`` runs along the first pixel coordinate, ``b`` along the second, both from -N//2.
    """
    h, w, f = feat.shape
    half = n // 2
    cols = []
    for a in range(-half, half + 1):
        for b in range(-half, half + 1):
            cols.append(np.roll(feat, (-a, -b), axis=(0, 1)).reshape(h * w, f))
    return np.concatenate(cols, axis=1).astype(np.int64)


def _source_level(feat: np.ndarray, p: dict, k2: int, margins: tuple[int, int]) -> SourceLevel:
    """Appearance space of one exemplar level: quantized PCA and 2D k-coherent candidates,
    both of the neighbourhoods that keep ``margins`` from the edges."""
    n = int(p["neighborhood"])
    h, w, _ = feat.shape
    usable = usable_pixels((h, w), margins)
    vec = 3 * _neighborhoods(feat, n)  # voxels carry the sum of three exemplar colors
    most = min(int(p["max_dims"]), vec.shape[1], MAX_DIMS)
    covariance = exact_pca.covariance(vec if usable.all() else vec[usable])
    evals, evecs, total = exact_pca.principal_axes(covariance, most)
    frac = np.cumsum(evals) / total if total > 0 else np.ones_like(evals)
    dims = int(np.searchsorted(frac, float(p["variance"])) + 1)
    dims = min(int(np.clip(dims, int(p["min_dims"]), int(p["max_dims"]))), most)
    basis_f = evecs[:, :dims].T
    # Fix each component's sign, which an eigensolver leaves free.
    signs = np.sign(basis_f[np.arange(dims), np.argmax(np.abs(basis_f), axis=1)])
    basis_f *= signs[:, None]
    scale = BASIS_LIMIT / max(np.abs(basis_f).max(), 1e-12)
    basis = np.rint(basis_f * scale).astype(np.int64)
    acc = vec @ basis.T
    shift = max(0, int(np.abs(acc).max()).bit_length() - PROJ_BITS)
    proj = (acc >> shift).astype(np.int16)
    return SourceLevel(
        feat=feat,
        basis=basis.astype(np.int32),
        shift=shift,
        proj=proj,
        cand2d=_kcoherent(proj, h, w, k2, usable),
        margins=margins,
    )


def _kcoherent(proj: np.ndarray, h: int, w: int, k: int, usable: np.ndarray) -> np.ndarray:
    """2D k-coherent candidates: the pixel itself, then the most similar neighbourhoods
    farther than 2 pixels from it (Tong et al. 2002), all of them ``usable`` pixels; a
    pixel that is not usable itself leads with the usable one most like it."""
    npix = h * w
    idx = _nearest_usable(proj, usable, proj, 4 * k + 25)
    own = np.arange(npix)
    u0, v0 = np.divmod(own, w)
    u1, v1 = np.divmod(idx, w)
    du = np.abs(u1 - u0[:, None])
    dv = np.abs(v1 - v0[:, None])
    lead = np.where(usable, own, idx[:, 0])
    far = ((np.minimum(du, h - du) > 2) | (np.minimum(dv, w - dv) > 2)) & (idx != lead[:, None])
    out = np.repeat(lead[:, None], k, axis=1).astype(np.int32)
    # Each pixel's first k - 1 far ones, in order of similarity; rows with fewer keep the
    # lead in the slots left (a level of fewer usable pixels than k has fewer for all).
    first = np.argsort(~far, axis=1, kind="stable")[:, : k - 1]
    taken = np.arange(first.shape[1])[None, :] < far.sum(axis=1)[:, None]
    out[:, 1 : 1 + first.shape[1]][taken] = np.take_along_axis(idx, first, axis=1)[taken]
    return out


def _nearest_usable(database: np.ndarray, usable: np.ndarray, queries: np.ndarray,
                    k: int) -> np.ndarray:
    """:func:`nearest_rows` among the ``usable`` rows of ``database``, as indices of it."""
    if usable.all():
        return nearest_rows(database, queries, k)
    pool = np.flatnonzero(usable)
    return pool[nearest_rows(database[pool], queries, k)].astype(np.int32)


def _role_level(trio: list[SourceLevel], p: dict, k3: int,
                done_half: Callable[[], None]) -> RoleLevel:
    """3D candidates of the role-0 exemplar's pixels against roles 1 and 2 (4.1, 4.2);
    ``done_half`` is called after the crossbar search and after the coherence test."""
    half = int(p["neighborhood"]) // 2
    npix = trio[0].feat.shape[0] * trio[0].feat.shape[1]
    strips = [[pixel_strips(t.feat, axis, half) for axis in (0, 1)] for t in trio]
    # Role 0's second-coordinate strip meets role 1's first-coordinate strip; role 0's
    # first-coordinate strip meets role 2's second-coordinate strip.
    near1 = _nearest_strips(strips[1][0], trio[1].usable(), strips[0][1], p)
    near2 = _nearest_strips(strips[2][1], trio[2].usable(), strips[0][0], p)
    keep = min(int(p["keep"]), near1.shape[1] * near2.shape[1])
    dev = PRECOMPUTE_DEVICE
    keys = wp.full((npix, keep), np.iinfo(np.int64).max, dtype=wp.int64, device=dev)
    c1 = wp.zeros((npix, keep), dtype=wp.int32, device=dev)
    c2 = wp.zeros((npix, keep), dtype=wp.int32, device=dev)
    errors_of = wp.zeros((npix, keep), dtype=wp.int32, device=dev)
    count = wp.zeros(npix, dtype=wp.int32, device=dev)
    closing = wp.empty(near2.shape, dtype=wp.int32, device=dev)
    launch_ranges(
        _k.best_crossbar_triples,
        0,
        npix,
        [role_strips([a for pair in strips for a in pair]), wp.array(near1, device=dev),
         wp.array(near2, device=dev), closing],
        [keys, c1, c2, errors_of, count],
        min_items=MIN_SPLIT_PIXELS,
    )
    cand = np.stack([c1.numpy(), c2.numpy()], axis=2)
    done_half()
    cand, errors, cnt, fallback = _filter_coherent(cand, errors_of.numpy(), count.numpy(),
                                                   [t.size for t in trio], k3,
                                                   int(p["coherence_rounds"]))
    done_half()
    return RoleLevel(cand=cand, crossbar_errors=errors, count=cnt, fallback=fallback)


def _nearest_strips(database: np.ndarray, usable: np.ndarray, queries: np.ndarray,
                    p: dict) -> np.ndarray:
    """The S best-matching ``usable`` strips of ``database`` for each query strip (ANN
    search)."""
    return _nearest_usable(database, usable, queries, int(p["strips"]))


def nearest_rows(database: np.ndarray, queries: np.ndarray, k: int) -> np.ndarray:
    """Indices (Q, k) int32 of the ``k`` rows of ``database`` nearest to each of
    ``queries``, both integer-valued, nearest first and equally near rows by index.

    A k-d tree returns equally distant rows in an order of its own that may differ between
    SciPy builds, and integer features tie often; candidates decide every voxel's colour,
    so the order here is canonical: exact integer distances, the index as second key, and
    a query whose k-th distance ties with the farthest row retrieved is searched wider.
    Equal rows (a photo's flat or saturated areas, thousands alike) are searched as one,
    which stands for all of its members: each query's ties with them widened its search to
    the whole database (a 64 px photo, mostly flat, took 44 s and 4.4 GB).
    """
    db = np.asarray(database).astype(np.int64)
    q = np.asarray(queries).astype(np.int64)
    k = min(int(k), len(db))
    out = np.empty((len(q), k), np.int32)
    if len(q) == 0 or k == 0:
        return out
    rows, first, inverse, counts = np.unique(db, axis=0, return_index=True,
                                             return_inverse=True, return_counts=True)
    members = np.argsort(inverse.reshape(-1), kind="stable")  # by row, each by index
    starts = np.cumsum(counts) - counts
    tree = parallel.kd_tree(rows.astype(np.float64))
    todo = np.arange(len(q))
    want = min(len(rows), k + 8)
    while len(todo):
        unresolved = []
        # Queries in parts, so that a wide search holds about _NEAREST_ENTRIES rows at once.
        step = max(1, _NEAREST_ENTRIES // want)
        for part in np.split(todo, range(step, len(todo), step)):
            idx = parallel.nearest(tree, q[part].astype(np.float64), k=want)[1]
            idx = idx.reshape(len(part), want)
            rows_at_once = max(1, _DISTANCE_TERMS // (want * rows.shape[1]))
            d2 = np.concatenate([((q[part[lo:lo + rows_at_once], None, :]
                                   - rows[idx[lo:lo + rows_at_once]]) ** 2).sum(axis=2)
                                 for lo in range(0, len(part), rows_at_once)])
            order = np.lexsort((first[idx], d2), axis=-1)
            idx = np.take_along_axis(idx, order, axis=1)
            d2 = np.take_along_axis(d2, order, axis=1)
            # The retrieved row that holds each query's k-th nearest member.
            kth = np.argmax(np.cumsum(counts[idx], axis=1) >= k, axis=1)
            dk = d2[np.arange(len(part)), kth]
            # Rows not retrieved are at least as far as the farthest retrieved one.
            done = (dk < d2[:, -1]) | (want == len(rows))
            # Where the k nearest are rows of one member each, they are those members.
            alone = np.zeros(len(part), bool)
            if want >= k:  # else fewer distinct rows than k, some of several members
                alone = done & (counts[idx[:, :k]] == 1).all(axis=1)
                out[part[alone]] = first[idx[alone, :k]]
            rest = done & ~alone
            out[part[rest]] = _first_members(idx[rest], d2[rest], dk[rest], k, members,
                                             starts, counts)
            unresolved.append(part[~done])
        todo = np.concatenate(unresolved)
        want = min(len(rows), 2 * want)
    return out


def _first_members(idx: np.ndarray, d2: np.ndarray, dk: np.ndarray, k: int,
                   members: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Each query's ``k`` nearest database rows by (distance, index), from its retrieved
    distinct rows ``idx`` (sorted by distance, then first member) at squared distances
    ``d2``, all those up to the k-th member's ``dk`` among them; a distinct row's members
    are ``members[starts: starts + counts]``, by index."""
    below = d2 < dk[:, None]
    need = k - (counts[idx] * below).sum(axis=1, keepdims=True)  # taken from the dk tier
    # In the tier, the first ``need`` rows (by first member) each bring at most ``need``
    # members: any further member has ``need`` smaller ones before it.
    tier = (d2 == dk[:, None]) & (np.cumsum(d2 == dk[:, None], axis=1) <= need)
    take = np.where(below, counts[idx], np.where(tier, np.minimum(counts[idx], need), 0))
    per_query = take.sum(axis=1)
    out = np.empty((len(idx), k), np.int32)
    # Queries in parts of about _NEAREST_ENTRIES members (a query at least).
    ends = np.searchsorted(np.cumsum(per_query), np.arange(_NEAREST_ENTRIES, int(
        per_query.sum()), _NEAREST_ENTRIES), side="right")
    for lo, hi in itertools.pairwise([0, *np.unique(np.maximum(ends, 1)), len(idx)]):
        if hi <= lo:
            continue
        part = take[lo:hi].ravel()
        query = np.repeat(np.arange(hi - lo).repeat(idx.shape[1]), part)
        distance = np.repeat(d2[lo:hi].ravel(), part)
        offset = np.arange(int(part.sum())) - np.repeat(np.cumsum(part) - part, part)
        member = members[np.repeat(starts[idx[lo:hi].ravel()], part) + offset]
        ranked = member[np.lexsort((member, distance, query))]
        begin = np.cumsum(per_query[lo:hi]) - per_query[lo:hi]
        out[lo:hi] = ranked[begin[:, None] + np.arange(k)]
    return out


def _filter_coherent(
    cand: np.ndarray,
    errors: np.ndarray,
    count: np.ndarray,
    sizes: list[tuple[int, int]],
    k3: int,
    rounds: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Iterate the coherence test of section 4.2 down to at most ``k3`` candidates.

    Each round keeps the candidates with continuous coordinates in a neighbour's list in
    both other exemplars. A pixel that would lose all keeps its best and is flagged as a
    fallback. When a round removes nothing, or after ``rounds`` rounds, lists longer than
    ``k3`` are cut to their ``k3`` lowest crossbar errors and filtering resumes until a
    round removes nothing, so the final lists are coherent with each other (except at
    fallback pixels). Every round but the last removes candidates, so this ends.
    """
    cand, errors = cand.copy(), errors.copy()  # lists are reordered in place below
    npix, slots = cand.shape[:2]
    fallback = np.zeros(npix, bool)
    # A pixel's test reads only its neighbours' lists, and a list that passed keeps
    # passing while they stay the same: each round tests just the neighbours of the pixels
    # whose lists changed in the round before (all pixels at first).
    retest = np.ones(npix, bool)
    done = 0
    while True:
        listed = np.flatnonzero(retest)
        flags = np.arange(slots)[None, :] < count[:, None]
        flags[listed] = _continued(cand, count, sizes, listed)
        kept = flags.sum(axis=1)
        empty = kept == 0
        flags[empty, 0] = True  # keeps its best; a fallback pixel's list is that one already
        fallback |= empty
        kept = flags.sum(axis=1)
        done += 1
        before = count
        if np.array_equal(kept, count):
            if count.max() <= k3:
                break
            count = np.minimum(count, k3)
        else:
            shrunk = np.flatnonzero(kept != count)  # elsewhere the kept ones lead already
            order = np.argsort(~flags[shrunk], axis=1, kind="stable")
            cand[shrunk] = np.take_along_axis(cand[shrunk], order[:, :, None], axis=1)
            errors[shrunk] = np.take_along_axis(errors[shrunk], order, axis=1)
            count = kept
            if done >= rounds:
                # Stopping here would leave lists whose support was just removed; cut them
                # to k3 instead (the paper's "keep the first 12") and filter on to a fixpoint.
                count = np.minimum(count, k3)
        retest = _direct_neighbours(count != before, sizes[0])
    width_k = min(k3, cand.shape[1])
    cand = cand[:, :width_k].copy()
    errors = errors[:, :width_k].copy()
    count = np.minimum(count, width_k).astype(np.int32)
    invalid = np.arange(width_k)[None, :] >= count[:, None]
    # Unused slots repeat the best candidate so any reader stays in range.
    cand[invalid] = np.repeat(cand[:, :1], width_k, axis=1)[invalid]
    errors[invalid] = np.repeat(errors[:, :1], width_k, axis=1)[invalid]
    return cand.astype(np.int32), errors.astype(np.int32), count, fallback


def _continued(cand: np.ndarray, count: np.ndarray, sizes: list[tuple[int, int]],
               listed: np.ndarray) -> np.ndarray:
    """Flags (len(listed), K) of the valid candidates of the ``listed`` pixels whose
    coordinates continue a candidate of a direct neighbour in both other exemplars
    (section 4.2); ``cand`` (P, K, 2) holds the role-1 and role-2 pixels of each list."""
    dev = PRECOMPUTE_DEVICE
    counts = wp.array(count, dtype=wp.int32, device=dev)
    coords = []
    for role in (1, 2):
        coords.append(_k.CandidateCoords())
        u, v = np.divmod(cand[:, :, role - 1], sizes[role][1])
        coords[-1].u, coords[-1].v = (wp.array(a.astype(np.int32), device=dev) for a in (u, v))
        coords[-1].count = counts
    # A bitmap row of the larger exemplar's pixels per pixel tested at once, in batches of
    # at most _MARK_BYTES.
    words = -(-max(h * w for h, w in sizes[1:]) // 32)
    batch = max(1, min(len(listed), _MARK_BYTES // (4 * words)))
    keep = wp.zeros((len(listed), cand.shape[1]), dtype=wp.int32, device=dev)
    inputs = [wp.array(listed.astype(np.int32), dtype=wp.int32, device=dev), *coords,
              wp.vec3i(*[s[0] for s in sizes]), wp.vec3i(*[s[1] for s in sizes]),
              wp.zeros((batch, words), dtype=wp.uint32, device=dev)]
    for lo in range(0, len(listed), batch):
        launch_ranges(_k.coherent_candidates, lo, min(lo + batch, len(listed)),
                      [lo, *inputs], [keep], min_items=MIN_SPLIT_PIXELS)
    return keep.numpy().astype(bool)


def _direct_neighbours(marked: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Pixels with a marked direct (4-connected, toroidal) neighbour, as a flat mask."""
    grid = marked.reshape(size)
    near = np.zeros_like(grid)
    for axis in (0, 1):
        for step in (-1, 1):
            near |= np.roll(grid, step, axis=axis)
    return near.reshape(-1)
