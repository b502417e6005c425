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
from dataclasses import dataclass, field
from functools import cache, cached_property
from numbers import Real
from pathlib import Path

import numpy as np
import warp as wp
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from kernels import candidates as _k
from kernels import common as _common
from kernels.synthesis import BASIS_LIMIT, BLOCK, EXACT_ROW_TERMS, MAX_DIMS, PROJ_LIMIT
from warptex import exact_pca, parallel, warp_runtime
from warptex.archive import (
    ArchiveError,
    folder_problem,
    overwrite_problem,
    read_archive,
    write_archive,
)
from warptex.code_digest import code_digest, module_sources
from warptex.exemplar import (
    Exemplar,
    ExemplarError,
    as_exemplar,
    axis_triple,
    check_same_channels,
    wrapping_edges,
)
from warptex.machine import memory_problem
from warptex.parallel import launch_ranges
from warptex.settings import (
    check_file_name,
    check_flag,
    check_tileable,
    is_integer,
    names_folder,
)
from warptex.thread_warnings import warn
from warptex.warp_runtime import init_warp

FORMAT_VERSION = 6  # 3: nearest neighbours tie-broken by index, whatever SciPy's k-d tree does;
# 4: the PCA basis the same on every CPU (no LAPACK; BLAS only where its sums are exact);
# 5: margins that candidates keep from the edges of exemplars that do not tile;
# 6: one quantization range for all color channels (section 5.2's L2 norm on colors)
PROJ_BITS = PROJ_LIMIT.bit_length()  # projections quantized to signed PROJ_BITS + 1 bits
FILE_MAGIC = b"WARPTEXC"
CACHE_PREFIX, CACHE_SUFFIX = "candidates-", ".wtc"
# A pixel's crossbar search scores S^2 triples and its coherence test reads its neighbours'
# lists: even the coarsest level's 64 pixels are worth splitting over the cores.
_MIN_SPLIT_PIXELS = 64
_MARK_BYTES = 16 << 20  # scratch bitmaps of the coherence test
# A nearest-rows search holds at most so many retrieved rows at once, and so many terms of
# their distances (int64), however widely ties make it search.
_NEAREST_ENTRIES = 1 << 22
_DISTANCE_TERMS = 1 << 21
# Pre-computation runs once per exemplar and is cached, so its kernels stay on the host,
# beside the k-d tree searches whose results they read.
_DEVICE = "cpu"
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

DEFAULT_PARAMS: dict[str, object] = {
    "neighborhood": 5,  # N
    "strips": 65,  # S
    "keep": 100,  # best crossbar triples kept before coherence filtering
    "candidates_3d": 12,  # 3D candidates kept per pixel (synthesis uses 4 at the finest level)
    "candidates_2d": 4,  # 2D k-coherent candidates per pixel at coarse levels
    "candidates_2d_finest": 2,
    "variance": 0.95,  # PCA variance kept
    "min_dims": 8,
    "max_dims": 12,
    "coherence_rounds": 16,
    # "auto": candidates keep away from the edges that form a seam (Exemplar.seams), and the
    # pyramid does not blur across them; True: every exemplar is a torus, as in the paper;
    # False: no edge is continued.
    "tileable": "auto",
}


# What each integer parameter may be. Beyond these a pre-computation failed deep inside (keep
# 0 crashed a kernel), ran for hours (the crossbar search grows as strips^2) or made
# candidates the engine refuses (it reads at most BLOCK voxels away, so N <= 2 BLOCK + 1).
_PARAM_RANGES: dict[str, tuple[int, int]] = {
    "neighborhood": (3, 2 * BLOCK + 1),
    "strips": (1, 256),
    "keep": (1, 65535),
    "candidates_3d": (1, 255),  # counts of 3D candidates are stored as bytes
    "candidates_2d": (1, 64),
    "candidates_2d_finest": (1, 64),
    "min_dims": (1, MAX_DIMS),
    "max_dims": (1, MAX_DIMS),
    "coherence_rounds": (1, 1024),
}


class CandidateCacheError(ArchiveError):
    """A candidate file is corrupt, truncated, of another version or another format."""


@dataclass
class SourceLevel:
    """One exemplar at one pyramid level: quantized features and appearance space."""

    feat: np.ndarray  # (h, w, F) uint8, features quantized to [0, 255]
    basis: np.ndarray  # (D, N*N*F) int32, quantized PCA basis
    shift: int  # projections are (basis . 3*feat) >> shift
    proj: np.ndarray  # (h*w, D) int16, projected neighbourhoods of 3*feat
    cand2d: np.ndarray  # (h*w, K2) int32 pixel indices, self first where usable
    # Rows at the top and bottom, columns at the left and right that no candidate holds: an
    # N x N neighbourhood centred farther in does not cross a seam of the photo.
    margins: tuple[int, int]

    @property
    def size(self) -> tuple[int, int]:
        return int(self.feat.shape[0]), int(self.feat.shape[1])

    def usable(self) -> np.ndarray:
        """(h*w,) bool: the pixels a candidate may hold, those outside the margins."""
        return _usable(self.size, self.margins)


@dataclass
class RoleLevel:
    """3D candidates of the pixels of one exemplar role at one level (sections 4.1-4.2)."""

    cand: np.ndarray  # (h*w, K3, 2) int32: pixel in the next and the next-next exemplar
    crossbar_errors: np.ndarray  # (h*w, K3) int32 crossbar error, ascending
    count: np.ndarray  # (h*w,) int32 valid candidates
    fallback: np.ndarray  # (h*w,) bool: no coherent candidate was found, best one kept


@dataclass(eq=False, repr=False)
class CandidateSet:
    """Pre-computed candidates for three exemplars (one per axis), all pyramid levels
    (Dong 2008, section 4: the 3D candidates; section 4.3: the candidate slab).

    ``sources[j]`` are the distinct exemplars, ``axis_source[k]`` which one lies on
    axis k. ``roles[l][r]`` holds the 3D candidates; there is one role when the same
    exemplar lies on all three axes, else three (role k owned by axis k).
    """

    params: dict
    digests: tuple[str, str, str]
    axis_source: tuple[int, int, int]
    colors: list[np.ndarray]  # per source, finest level, (H, W, C) float32
    sources: list[list[SourceLevel]]  # [level][source]
    roles: list[list[RoleLevel]]  # [level][role]
    stats: dict = field(default_factory=dict)
    # The exemplars' names (x, y, z) when computed, with what set them apart from their
    # files (:func:`_exemplar_label`), for people listing cache files; the digests, not the
    # names, say what the candidates are of.
    names: tuple[str, ...] = field(default=(), compare=False)
    # How precompute got these: "loaded" from its cache, "written" to it, "not written"
    # (the cache could not be written), or "" without a cache. Not saved in files.
    cache_status: str = field(default="", compare=False, repr=False)
    # Digest of the code that computed them (``warptex.code_digest``), which the cache
    # compares with its own; "" where not recorded.
    code: str = field(default="", compare=False, repr=False)

    def __repr__(self) -> str:
        # Not the fields': their arrays run to thousands of lines in a notebook.
        names = ", ".join(dict.fromkeys(self.names or [d[:12] for d in self.digests]))
        return (f"CandidateSet({names}; {self.num_levels} levels, {self.channels} channels, "
                f"{self.nbytes() / 2**20:.1f} MiB)")

    def __eq__(self, other: object) -> bool:
        """The same candidates: the same parameters and everything synthesis reads."""
        if not isinstance(other, CandidateSet):
            return NotImplemented
        return self.params == other.params and self.content_digest == other.content_digest

    @property
    def num_levels(self) -> int:
        return len(self.sources)

    @property
    def channels(self) -> int:
        return int(self.colors[0].shape[2])

    @property
    def shared(self) -> bool:
        return len(self.roles[0]) == 1

    def role_of_axis(self, axis: int) -> int:
        return 0 if self.shared else axis

    def nbytes(self) -> int:
        """Bytes of the arrays a candidate file holds (its header and layout come on top)."""
        return sum(a.nbytes for a in _flatten(self).values())

    @cached_property
    def content_digest(self) -> str:
        """SHA-256 of everything synthesis reads from these candidates, so that a brick store
        is never mixed with candidates computed otherwise under the same exemplars and
        parameters (by another warptex version, or a candidate file edited since)."""
        flat = _flatten(self)
        layout = {"axis_source": list(self.axis_source), **_source_layout(self)}
        digest = hashlib.sha256(json.dumps(layout).encode())
        for name in sorted(flat.keys() - {"meta"}):
            array = np.ascontiguousarray(flat[name])
            digest.update(f"{name} {array.dtype.str} {array.shape}".encode())
            digest.update(array.data)
        return digest.hexdigest()

    def save(self, path: str | Path) -> None:
        """Write a versioned, checksummed file atomically (temporary name, then rename).
        A path that names a folder or holds a file of another kind, which the write would
        destroy, is refused (CandidateCacheError)."""
        self._write(check_candidate_path(path))

    def _write(self, path: Path) -> None:
        """:meth:`save` unchecked: the cache overwrites its damaged files."""
        write_archive(path, FILE_MAGIC, FORMAT_VERSION, _flatten(self))

    @classmethod
    def load(cls, path: str | Path) -> CandidateSet:
        """Read a file written by :meth:`save`; raise CandidateCacheError if it is damaged."""
        path = check_file_name("path", path)
        return _unflatten(_read_file(path), path)


def check_feature_channels(channels: int,
                           neighborhood: int = DEFAULT_PARAMS["neighborhood"]) -> None:
    """Refuse exemplars of more ``channels`` (colors and a feature distance) than the
    synthesis engine's exact projections of ``neighborhood``-voxel rows add up: the
    engine is what candidates are for, and they take minutes to pre-compute."""
    if neighborhood * channels > EXACT_ROW_TERMS:
        raise ValueError(f"{channels} feature channels are too many for exact projections "
                         f"with {neighborhood}-voxel neighbourhoods (at most "
                         f"{EXACT_ROW_TERMS // neighborhood})")


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
    stderr; None shows it when stderr is a terminal.
    """
    check_flag("cache", cache)
    if progress is not None:
        check_flag("progress", progress)
    exemplars = [as_exemplar(e) for e in axis_triple(ex, ey, ez)]
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


def _cached(path: Path, exemplars: list[Exemplar], params: dict) -> CandidateSet:
    """The candidates cached at ``path``, if they are those of ``exemplars`` and ``params``."""
    return _with_crossbar_errors(_cached_set(path, exemplars, params))


def _cached_set(path: Path, exemplars: list[Exemplar], params: dict) -> CandidateSet:
    """The candidates of the cache file ``path`` (crossbar errors not yet derived), whole
    (checksummed), laid out as the kernels index them, and of ``exemplars`` and
    ``params``; CandidateCacheError otherwise."""
    arrays = _read_file(path)
    meta = _meta(arrays, path)
    found = {"digests": meta["digests"], "params": meta["params"]}
    # Through JSON, as the file's went: tuples become lists, so equal compares equal.
    wanted = json.loads(json.dumps({"digests": [e.digest() for e in exemplars], "params": params}))
    if wanted != found:
        raise CandidateCacheError(f"{path}: holds the candidates of other exemplars or "
                                  "parameters (a copied or renamed cache file)")
    if not computed_here(meta):
        raise CandidateCacheError(f"{path}: holds candidates another version of warptex "
                                  "computed (a copied or renamed cache file)")
    return _laid_out(arrays, path)


def read_cache_meta(path: Path, version: int = FORMAT_VERSION) -> dict:
    """What a whole (checksummed) candidate file of this format version (or of
    ``version``, where its record reads alike) says it holds: ``digests`` and ``params``,
    which name it (:func:`cache_file_name`), and ``names`` where recorded;
    CandidateCacheError otherwise, and, for this version, where its arrays do not fit
    together (a file :func:`precompute` would refuse is no file in use)."""
    arrays = _read_file(path, version)
    if version == FORMAT_VERSION:
        _laid_out(arrays, path)
    return _meta(arrays, path)


def _read_file(path: str | Path, version: int = FORMAT_VERSION) -> dict[str, np.ndarray]:
    """The arrays of a whole candidate file of this format version, or of ``version``
    (CandidateCacheError otherwise), before its contents are checked."""
    return read_archive(path, FILE_MAGIC, version, "candidate", CandidateCacheError)


def _meta(arrays: dict[str, np.ndarray], path: Path) -> dict:
    try:
        meta = json.loads(bytes(arrays["meta"]).decode())
        if not isinstance(meta, dict) or not {"digests", "params"} <= meta.keys():
            raise KeyError("digests, params")
        # Listings read these as they come: a hand-made record must not fail them.
        if not (_strings(meta["digests"]) and isinstance(meta["params"], dict)
                and _strings(meta.get("names", []))):
            raise ValueError("digests, params or names of another type")
    except (ValueError, KeyError) as e:
        raise CandidateCacheError(f"{path}: unreadable candidate data ({e})") from None
    return meta


def _strings(value: object) -> bool:
    return isinstance(value, list) and all(isinstance(v, str) for v in value)


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


def cache_path(exemplars: list[Exemplar], params: dict) -> Path:
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


def cache_file_name(digests: Sequence[str], params: dict) -> str:
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
    """This module, its kernels and their building blocks, how they are launched (ranges
    of a launch split over threads), its PCA and the exemplar's pyramid; None where a
    module has no source file."""
    return module_sources((sys.modules[__name__], _k, _common, parallel, warp_runtime,
                           exact_pca, sys.modules[Exemplar.__module__]))


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


def resolved_params(params: dict) -> dict:
    """Candidate parameters ``params`` with the defaults of the others, each checked
    against :data:`_PARAM_RANGES` (and made a plain int or float, as cache keys and files
    hold them): what :func:`precompute` keys its cache by."""
    unknown = set(params) - set(DEFAULT_PARAMS)
    if unknown:
        raise TypeError(f"unknown candidate parameter(s): {', '.join(sorted(unknown))}")
    p = {**DEFAULT_PARAMS, **params}
    for name, (low, high) in _PARAM_RANGES.items():
        value = p[name]
        if not is_integer(value):
            raise TypeError(f"{name} must be an integer, got {value!r}")
        if not low <= value <= high:
            raise ValueError(f"{name} must be within [{low}, {high}], got {value}")
        p[name] = int(value)
    if p["neighborhood"] % 2 == 0:
        raise ValueError(f"neighborhood must be odd, got {p['neighborhood']}")
    if p["min_dims"] > p["max_dims"]:
        raise ValueError(f"min_dims ({p['min_dims']}) must not exceed max_dims "
                         f"({p['max_dims']})")
    variance = p["variance"]
    if isinstance(variance, bool) or not isinstance(variance, Real):
        raise TypeError(f"variance must be a number, got {variance!r}")
    if not 0 < variance <= 1:
        raise ValueError(f"variance (the share of PCA variance kept) must be within (0, 1], "
                         f"got {variance!r}")
    p["variance"] = float(variance)
    p["tileable"] = check_tileable(p["tileable"])
    return p


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
            lvl_roles.append(_role_level(_trio(lvl_sources, axis_source, role), p, k3,
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


def _usable(size: tuple[int, int], margins: tuple[int, int]) -> np.ndarray:
    """(h*w,) bool: the pixels of an ``size`` exemplar level outside ``margins``."""
    (h, w), (mu, mv) = size, margins
    inside = np.zeros((h, w), bool)
    inside[mu:h - mu, mv:w - mv] = True
    return inside.reshape(-1)


def _trio(sources: list, axis_source: tuple, role: int) -> list:
    """The sources of role ``role``'s triples in order: its own exemplar's (the axis
    ``role``), then those of the next two axes."""
    return [sources[axis_source[(role + k) % 3]] for k in range(3)]


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
    usable = _usable((h, w), margins)
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


def _strips(feat: np.ndarray, axis: int, half: int) -> np.ndarray:
    """N x 1 strips through every pixel along pixel coordinate ``axis``, (h*w, N*F)."""
    h, w, f = feat.shape
    cols = [np.roll(feat, -t, axis=axis).reshape(h * w, f) for t in range(-half, half + 1)]
    return np.concatenate(cols, axis=1).astype(np.float32)


def _role_level(trio: list[SourceLevel], p: dict, k3: int,
                done_half: Callable[[], None]) -> RoleLevel:
    """3D candidates of the role-0 exemplar's pixels against roles 1 and 2 (4.1, 4.2);
    ``done_half`` is called after the crossbar search and after the coherence test."""
    half = int(p["neighborhood"]) // 2
    npix = trio[0].feat.shape[0] * trio[0].feat.shape[1]
    strips = [[_strips(t.feat, axis, half) for axis in (0, 1)] for t in trio]
    # Role 0's second-coordinate strip meets role 1's first-coordinate strip; role 0's
    # first-coordinate strip meets role 2's second-coordinate strip.
    near1 = _nearest_strips(strips[1][0], trio[1].usable(), strips[0][1], p)
    near2 = _nearest_strips(strips[2][1], trio[2].usable(), strips[0][0], p)
    keep = min(int(p["keep"]), near1.shape[1] * near2.shape[1])
    dev = _DEVICE
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
        [_role_strips([a for pair in strips for a in pair]), wp.array(near1, device=dev),
         wp.array(near2, device=dev), closing],
        [keys, c1, c2, errors_of, count],
        min_items=_MIN_SPLIT_PIXELS,
    )
    cand = np.stack([c1.numpy(), c2.numpy()], axis=2)
    done_half()
    cand, errors, cnt, fallback = _filter_coherent(cand, errors_of.numpy(), count.numpy(),
                                                   [t.size for t in trio], k3,
                                                   int(p["coherence_rounds"]))
    done_half()
    return RoleLevel(cand=cand, crossbar_errors=errors, count=cnt, fallback=fallback)


def _crossbar_errors(trio: list[SourceLevel], cand: np.ndarray, half: int) -> np.ndarray:
    """Crossbar errors (P, K) int32 of stored candidates (section 4.1). They are derived
    data: files keep only the triples, and loading recomputes the errors."""
    init_warp()
    dev = _DEVICE
    strips = _role_strips([_strips(t.feat, axis, half) for t in trio for axis in (0, 1)])
    errors = wp.zeros(cand.shape[:2], dtype=wp.int32, device=dev)
    pairs = [wp.array(np.ascontiguousarray(cand[:, :, i]), dtype=wp.int32, device=dev)
             for i in (0, 1)]
    launch_ranges(_k.candidate_crossbar_errors, 0, cand.shape[0], [strips, *pairs], [errors],
                  per_item=cand.shape[1], min_items=_MIN_SPLIT_PIXELS)
    return errors.numpy()


def _role_strips(strips: list[np.ndarray]) -> _k.RoleStrips:
    """The strips of roles 0, 1 and 2 along their first and second coordinates, in that
    order, as the kernels take them."""
    out = _k.RoleStrips()
    (out.own_first, out.own_second, out.next_first, out.next_second, out.nnext_first,
     out.nnext_second) = (wp.array(a.astype(np.int32), device=_DEVICE) for a in strips)
    return out


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
    tree = cKDTree(rows.astype(np.float64))
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
    dev = _DEVICE
    coords = []
    for role in (1, 2):
        u, v = np.divmod(cand[:, :, role - 1], sizes[role][1])
        coords += [wp.array(a.astype(np.int32), device=dev) for a in (u, v)]
    # A bitmap row of the larger exemplar's pixels per pixel tested at once, in batches of
    # at most _MARK_BYTES.
    words = -(-max(h * w for h, w in sizes[1:]) // 32)
    batch = max(1, min(len(listed), _MARK_BYTES // (4 * words)))
    keep = wp.zeros((len(listed), cand.shape[1]), dtype=wp.int32, device=dev)
    inputs = [wp.array(listed.astype(np.int32), dtype=wp.int32, device=dev), *coords,
              wp.array(count, dtype=wp.int32, device=dev),
              wp.vec3i(*[s[0] for s in sizes]), wp.vec3i(*[s[1] for s in sizes]),
              wp.zeros((batch, words), dtype=wp.uint32, device=dev)]
    for lo in range(0, len(listed), batch):
        launch_ranges(_k.coherent_candidates, lo, min(lo + batch, len(listed)),
                      [lo, *inputs], [keep], min_items=_MIN_SPLIT_PIXELS)
    return keep.numpy().astype(bool)


def _direct_neighbours(marked: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Pixels with a marked direct (4-connected, toroidal) neighbour, as a flat mask."""
    grid = marked.reshape(size)
    near = np.zeros_like(grid)
    for axis in (0, 1):
        for step in (-1, 1):
            near |= np.roll(grid, step, axis=axis)
    return near.reshape(-1)


def _source_layout(cs: CandidateSet) -> dict[str, list]:
    """Each level's sources' projection shifts and candidate margins, as the files and
    the content digest record them."""
    return {"shifts": [[s.shift for s in lvl] for lvl in cs.sources],
            "margins": [[list(s.margins) for s in lvl] for lvl in cs.sources]}


def check_candidate_path(path: str | Path) -> Path:
    """``path`` as a Path, after a CandidateCacheError where it names a folder or holds a
    file of another kind, which saving candidates there would destroy."""
    target = check_file_name("path", path)
    problem = ("names a folder, not a file" if isinstance(path, str) and names_folder(path)
               else overwrite_problem(target, FILE_MAGIC, "candidate"))
    if problem is not None:
        raise CandidateCacheError(f"{path}: {problem}")
    return target


def _flatten(cs: CandidateSet) -> dict[str, np.ndarray]:
    meta = {
        "params": cs.params,
        "digests": list(cs.digests),
        "axis_source": list(cs.axis_source),
        "num_levels": cs.num_levels,
        "num_sources": len(cs.colors),
        "num_roles": len(cs.roles[0]),
        **_source_layout(cs),
        "stats": cs.stats,
        "names": list(cs.names),
        "code": cs.code,
    }
    out: dict[str, np.ndarray] = {"meta": np.frombuffer(json.dumps(meta).encode(), np.uint8)}
    for j, c in enumerate(cs.colors):
        out[f"colors/{j}"] = c
    for lv in range(cs.num_levels):
        for j, s in enumerate(cs.sources[lv]):
            out[f"L{lv}/S{j}/feat"] = s.feat
            out[f"L{lv}/S{j}/basis"] = s.basis.astype(np.int8)
            out[f"L{lv}/S{j}/proj"] = s.proj
            out[f"L{lv}/S{j}/cand2d"] = _compact_index(s.cand2d)
        for r, role in enumerate(cs.roles[lv]):
            out[f"L{lv}/R{r}/cand"] = _compact_index(role.cand)
            out[f"L{lv}/R{r}/count"] = role.count.astype(np.uint8)
            out[f"L{lv}/R{r}/fallback"] = np.packbits(role.fallback)
    return out


def _stored_int32(a: np.ndarray) -> np.ndarray:
    """A file's integer array as int32, after ValueError where it holds other numbers:
    narrowed unchecked, 2^32 + 5 would read as 5 and pass the layout's bounds."""
    if a.dtype.kind not in "iu" or not _within(a, -(2**31), 2**31 - 1):
        raise ValueError(f"integers within int32 expected, got {a.dtype}")
    return a.astype(np.int32)


def _stored_int(value: object) -> int:
    """A file's recorded integer, after ValueError where it is another kind of number,
    which int() would truncate."""
    if not isinstance(value, int) or isinstance(value, bool):
        raise ValueError(f"an integer expected, got {value!r}")
    return value


def _stored_flags(packed: np.ndarray, count: int) -> np.ndarray:
    """``count`` flags packed 8 to a byte, after ValueError where there are other than
    enough bytes (unpackbits pads a short array with zeros)."""
    if packed.dtype != np.uint8 or packed.shape != (-(-count // 8),):
        raise ValueError(f"{count} packed flags expected, got {packed.dtype} {packed.shape}")
    return np.unpackbits(packed, count=count).astype(bool)


def _stored_margins(margins: object) -> tuple[int, int]:
    """A source level's margins as a file holds them: two non-negative integers."""
    if not (isinstance(margins, list) and len(margins) == 2
            and all(isinstance(m, int) and m >= 0 for m in margins)):
        raise ValueError(f"margins {margins!r}")
    return margins[0], margins[1]


def _compact_index(a: np.ndarray) -> np.ndarray:
    return a.astype(np.uint16) if a.max(initial=0) < 65536 else a.astype(np.int32)


def _unflatten(d: dict[str, np.ndarray], path: str | Path) -> CandidateSet:
    return _with_crossbar_errors(_laid_out(d, path))


def _laid_out(d: dict[str, np.ndarray], path: str | Path) -> CandidateSet:
    """The candidates of a file's arrays ``d``, after CandidateCacheError where they do not
    fit together as the kernels index them."""
    # A checksummed file's layout may still be another's: a newer warptex's parameter, a
    # list too short or a number of another type fail as TypeError or IndexError.
    try:
        return _from_arrays(d)
    except (ValueError, LookupError, TypeError) as e:
        raise CandidateCacheError(f"{path}: unreadable candidate data ({e})") from None


def _with_crossbar_errors(cs: CandidateSet) -> CandidateSet:
    """``cs`` with each role's crossbar errors, which files leave out as the triples
    decide them."""
    half = int(cs.params["neighborhood"]) // 2
    for lv in range(cs.num_levels):
        for r, role in enumerate(cs.roles[lv]):
            trio = _trio(cs.sources[lv], cs.axis_source, r)
            role.crossbar_errors = _crossbar_errors(trio, role.cand, half)
    return cs


def _from_arrays(d: dict[str, np.ndarray]) -> CandidateSet:
    meta = json.loads(bytes(d["meta"]).decode())
    nl, ns, nr = meta["num_levels"], meta["num_sources"], meta["num_roles"]
    colors = [d[f"colors/{j}"] for j in range(ns)]
    sources, roles = [], []
    for lv in range(nl):
        lvl_src = []
        for j in range(ns):
            lvl_src.append(
                SourceLevel(
                    feat=d[f"L{lv}/S{j}/feat"],
                    basis=_stored_int32(d[f"L{lv}/S{j}/basis"]),
                    shift=_stored_int(meta["shifts"][lv][j]),
                    proj=d[f"L{lv}/S{j}/proj"],
                    cand2d=_stored_int32(d[f"L{lv}/S{j}/cand2d"]),
                    margins=_stored_margins(meta["margins"][lv][j]),
                )
            )
        lvl_roles = []
        for r in range(nr):
            npix = d[f"L{lv}/R{r}/count"].shape[0]
            lvl_roles.append(
                RoleLevel(
                    cand=_stored_int32(d[f"L{lv}/R{r}/cand"]),
                    # From the triples: _with_crossbar_errors.
                    crossbar_errors=np.zeros(0, np.int32),
                    count=_stored_int32(d[f"L{lv}/R{r}/count"]),
                    fallback=_stored_flags(d[f"L{lv}/R{r}/fallback"], npix),
                )
            )
        sources.append(lvl_src)
        roles.append(lvl_roles)
    cs = CandidateSet(
        params=meta["params"],
        digests=tuple(meta["digests"]),
        axis_source=tuple(meta["axis_source"]),
        colors=colors,
        sources=sources,
        roles=roles,
        stats=meta["stats"],
        names=tuple(meta.get("names", ())),
        code=str(meta.get("code", "")),
    )
    _check_layout(cs)
    return cs


def _check_layout(cs: CandidateSet) -> None:
    """ValueError unless a loaded set's arrays fit together as the kernels index them: a
    file that passes its checksum but was written by other means (candidate files travel
    between machines) would send them out of bounds."""
    resolved_params(cs.params)
    n = int(cs.params["neighborhood"])
    sources = len(cs.colors)
    if (len(cs.axis_source) != 3 or not all(0 <= j < sources for j in cs.axis_source)
            or len(cs.roles[0]) != (1 if len(set(cs.axis_source)) == 1 else 3)):
        raise ValueError(f"axes {cs.axis_source} of {sources} exemplars, {len(cs.roles[0])} roles")
    for j, colors in enumerate(cs.colors):
        if (colors.ndim != 3 or colors.shape[:2] != cs.sources[-1][j].size
                or colors.shape[2] != cs.colors[0].shape[2] or colors.dtype != np.float32
                or not np.isfinite(colors).all()):
            raise ValueError(f"colors of exemplar {j}: {colors.dtype} {colors.shape}")
    for lv in range(cs.num_levels):
        # The kernels take one row width for every exemplar's 2D candidates and every
        # role's 3D ones: the first's.
        k2, k3 = cs.sources[lv][0].cand2d.shape[1:2], cs.roles[lv][0].cand.shape[1:2]
        for j, s in enumerate(cs.sources[lv]):
            pixels, dims = s.size[0] * s.size[1], s.basis.shape[0]
            if (s.feat.ndim != 3 or s.feat.shape[2] != cs.sources[0][0].feat.shape[2]
                    or s.feat.dtype != np.uint8 or s.proj.dtype != np.int16
                    or s.basis.shape[1:] != (n * n * s.feat.shape[2],)
                    # Projections are exact sums only of basis terms within +-127 (the
                    # kernels' EXACT_ROW_TERMS): any order of adding gives them, CPU or GPU.
                    or not _within(s.basis, -BASIS_LIMIT, BASIS_LIMIT)
                    or not 1 <= dims <= MAX_DIMS or s.proj.shape != (pixels, dims)
                    or not _within(s.proj, -PROJ_LIMIT - 1, PROJ_LIMIT)
                    or not 0 <= s.shift < 32
                    or s.cand2d.ndim != 2 or s.cand2d.shape[0] != pixels
                    or s.cand2d.shape[1:2] != k2 or k2[0] < 1
                    or not _indices_below(s.cand2d, pixels)):
                raise ValueError(f"level {lv}, exemplar {j}: arrays that do not fit together")
        for r, role in enumerate(cs.roles[lv]):
            owner, *others = (p.size[0] * p.size[1] for p in _trio(cs.sources[lv],
                                                                    cs.axis_source, r))
            if (role.cand.ndim != 3 or role.cand.shape[0] != owner or role.cand.shape[2] != 2
                    or role.cand.shape[1:2] != k3 or k3[0] < 1
                    or role.count.shape != (owner,) or role.fallback.shape != (owner,)
                    or not _indices_below(role.count, role.cand.shape[1] + 1)
                    or not all(_indices_below(role.cand[..., k], others[k]) for k in (0, 1))):
                raise ValueError(f"level {lv}, role {r}: 3D candidates that do not fit")


def _within(a: np.ndarray, low: int, high: int) -> bool:
    """Whether every entry of ``a`` lies in [low, high]. Projections reach -PROJ_LIMIT - 1
    where precompute's shift rounds a negative sum down."""
    return a.size == 0 or (int(a.min()) >= low and int(a.max()) <= high)


def _indices_below(a: np.ndarray, limit: int) -> bool:
    """Whether every entry of ``a`` indexes one of ``limit`` pixels."""
    return _within(a, 0, limit - 1)
