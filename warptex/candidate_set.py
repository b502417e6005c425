"""What a candidate set holds (Dong 2008, section 4: the 3D candidates of every pixel of
every pyramid level; 4.3: the candidate slab that synthesis reads), the parameters that
decide it, and its file.

A file keeps the triples, the 2D candidates and each level's appearance space; the crossbar
errors (4.1) are derived from the triples when it is read. A file that passes its checksum
is still checked to fit together as the kernels index it: candidate files travel between
machines, and one written by other means would send the kernels out of bounds.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from numbers import Real
from pathlib import Path
from typing import TypedDict

import numpy as np
import warp as wp

from kernels import candidates as _k
from kernels.synthesis import BASIS_LIMIT, BLOCK, EXACT_ROW_TERMS, MAX_DIMS, PROJ_LIMIT
from warptex.archive import ArchiveError, overwrite_problem, read_archive, write_archive
from warptex.parallel import launch_ranges
from warptex.settings import check_file_name, check_tileable, is_integer, names_folder
from warptex.warp_runtime import init_warp

FORMAT_VERSION = 6  # 3: nearest neighbours tie-broken by index, whatever SciPy's k-d tree does;
# 4: the PCA basis the same on every CPU (no LAPACK; BLAS only where its sums are exact);
# 5: margins that candidates keep from the edges of exemplars that do not tile;
# 6: one quantization range for all color channels (section 5.2's L2 norm on colors)

FILE_MAGIC = b"WARPTEXC"
# A pixel's crossbar search scores S^2 triples and its coherence test reads its neighbours'
# lists: even the coarsest level's 64 pixels are worth splitting over the cores.
MIN_SPLIT_PIXELS = 64
# Pre-computation runs once per exemplar and is cached, so its kernels stay on the host,
# beside the k-d tree searches whose results they read.
PRECOMPUTE_DEVICE = "cpu"

class CandidateParams(TypedDict):
    """The parameters that decide a candidate set (Dong 2008, sections 4 and 6.2), as
    :data:`DEFAULT_PARAMS` gives them and candidate files and cache names record them."""

    neighborhood: int
    strips: int
    keep: int
    candidates_3d: int
    candidates_2d: int
    candidates_2d_finest: int
    variance: float
    min_dims: int
    max_dims: int
    coherence_rounds: int
    tileable: bool | str


DEFAULT_PARAMS: CandidateParams = {
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
        return usable_pixels(self.size, self.margins)


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

    params: CandidateParams
    digests: tuple[str, str, str]
    axis_source: tuple[int, int, int]
    colors: list[np.ndarray]  # per source, finest level, (H, W, C) float32
    sources: list[list[SourceLevel]]  # [level][source]
    roles: list[list[RoleLevel]]  # [level][role]
    stats: dict = field(default_factory=dict)
    # The exemplars' names (x, y, z) when computed, with what set them apart from their
    # files (``warptex.candidates._exemplar_label``), for people listing cache files; the
    # digests, not the names, say what the candidates are of.
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
        return with_crossbar_errors(laid_out(read_candidate_arrays(path), path))


def check_feature_channels(channels: int,
                           neighborhood: int = DEFAULT_PARAMS["neighborhood"]) -> None:
    """Refuse exemplars of more ``channels`` (colors and a feature distance) than the
    synthesis engine's exact projections of ``neighborhood``-voxel rows add up: the
    engine is what candidates are for, and they take minutes to pre-compute."""
    if neighborhood * channels > EXACT_ROW_TERMS:
        raise ValueError(f"{channels} feature channels are too many for exact projections "
                         f"with {neighborhood}-voxel neighbourhoods (at most "
                         f"{EXACT_ROW_TERMS // neighborhood})")


def read_cache_meta(path: Path, version: int = FORMAT_VERSION) -> dict:
    """What a whole (checksummed) candidate file of this format version (or of
    ``version``, where its record reads alike) says it holds: ``digests`` and ``params``,
    which name it (:func:`warptex.candidates.cache_file_name`), and ``names`` where recorded;
    CandidateCacheError otherwise, and, for this version, where its arrays do not fit
    together (a file :func:`~warptex.candidates.precompute` would refuse is no file in use)."""
    arrays = read_candidate_arrays(path, version)
    if version == FORMAT_VERSION:
        laid_out(arrays, path)
    return candidate_meta(arrays, path)


def read_candidate_arrays(path: str | Path, version: int = FORMAT_VERSION) -> dict[str, np.ndarray]:
    """The arrays of a whole candidate file of this format version, or of ``version``
    (CandidateCacheError otherwise), before its contents are checked."""
    return read_archive(path, FILE_MAGIC, version, "candidate", CandidateCacheError)


def candidate_meta(arrays: dict[str, np.ndarray], path: Path) -> dict:
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


def resolved_params(params: Mapping[str, object]) -> CandidateParams:
    """Candidate parameters ``params`` with the defaults of the others, each checked
    against :data:`_PARAM_RANGES` (and made a plain int or float, as cache keys and files
    hold them): what :func:`~warptex.candidates.precompute` keys its cache by."""
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


def usable_pixels(size: tuple[int, int], margins: tuple[int, int]) -> np.ndarray:
    """(h*w,) bool: the pixels of an ``size`` exemplar level outside ``margins``."""
    (h, w), (mu, mv) = size, margins
    inside = np.zeros((h, w), bool)
    inside[mu:h - mu, mv:w - mv] = True
    return inside.reshape(-1)


def role_trio(sources: list, axis_source: tuple, role: int) -> list:
    """The sources of role ``role``'s triples in order: its own exemplar's (the axis
    ``role``), then those of the next two axes."""
    return [sources[axis_source[(role + k) % 3]] for k in range(3)]


def pixel_strips(feat: np.ndarray, axis: int, half: int) -> np.ndarray:
    """N x 1 strips through every pixel along pixel coordinate ``axis``, (h*w, N*F)."""
    h, w, f = feat.shape
    cols = [np.roll(feat, -t, axis=axis).reshape(h * w, f) for t in range(-half, half + 1)]
    return np.concatenate(cols, axis=1).astype(np.float32)


def crossbar_errors_of(trio: list[SourceLevel], cand: np.ndarray, half: int) -> np.ndarray:
    """Crossbar errors (P, K) int32 of stored candidates (section 4.1). They are derived
    data: files keep only the triples, and loading recomputes the errors."""
    init_warp()
    dev = PRECOMPUTE_DEVICE
    strips = role_strips([pixel_strips(t.feat, axis, half) for t in trio for axis in (0, 1)])
    errors = wp.zeros(cand.shape[:2], dtype=wp.int32, device=dev)
    pairs = [wp.array(np.ascontiguousarray(cand[:, :, i]), dtype=wp.int32, device=dev)
             for i in (0, 1)]
    launch_ranges(_k.candidate_crossbar_errors, 0, cand.shape[0], [strips, *pairs], [errors],
                  per_item=cand.shape[1], min_items=MIN_SPLIT_PIXELS)
    return errors.numpy()


def role_strips(strips: list[np.ndarray]) -> _k.RoleStrips:
    """The strips of roles 0, 1 and 2 along their first and second coordinates, in that
    order, as the kernels take them."""
    out = _k.RoleStrips()
    (out.own_first, out.own_second, out.next_first, out.next_second, out.nnext_first,
     out.nnext_second) = (wp.array(a.astype(np.int32), device=PRECOMPUTE_DEVICE) for a in strips)
    return out


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


def laid_out(d: dict[str, np.ndarray], path: str | Path) -> CandidateSet:
    """The candidates of a file's arrays ``d``, after CandidateCacheError where they do not
    fit together as the kernels index them."""
    # A checksummed file's layout may still be another's: a newer warptex's parameter, a
    # list too short or a number of another type fail as TypeError or IndexError.
    try:
        return _from_arrays(d)
    except (ValueError, LookupError, TypeError) as e:
        raise CandidateCacheError(f"{path}: unreadable candidate data ({e})") from None


def with_crossbar_errors(cs: CandidateSet) -> CandidateSet:
    """``cs`` with each role's crossbar errors, which files leave out as the triples
    decide them."""
    half = int(cs.params["neighborhood"]) // 2
    for lv in range(cs.num_levels):
        for r, role in enumerate(cs.roles[lv]):
            trio = role_trio(cs.sources[lv], cs.axis_source, r)
            role.crossbar_errors = crossbar_errors_of(trio, role.cand, half)
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
                    # From the triples: with_crossbar_errors.
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
            trio = role_trio(cs.sources[lv], cs.axis_source, r)
            owner, *others = (p.size[0] * p.size[1] for p in trio)
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
