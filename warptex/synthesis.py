"""Lazy, spatially deterministic solid synthesis (Dong 2008, section 5).

A voxel's result is a pure function of its integer position, the candidates, the seed
and the parameters: never of what else was requested, of batch order or of cache state.
The host only orchestrates: it decides which sparse blocks each level works on and, voxel
by voxel, what each correction step must visit (section 5.2, dependency masks), and
launches the kernels of ``kernels.synthesis``.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from functools import cache
from numbers import Integral
from typing import NoReturn

import numpy as np
import warp as wp

from kernels import synthesis as _k
from kernels.common import KEY_BIAS, KEY_BITS
from warptex import machine
from warptex.candidate_set import CandidateSet, check_feature_channels
from warptex.dependencies import (
    apron_blocks,
    correction_steps,
    default_apron_blocks,
    neighborhood_shape,
)
from warptex.keysets import (
    cell_offsets,
    distinct_sorted,
    local_index,
    lookup,
    lookup_runs,
    pack,
    run_starts,
    unique,
    unpack,
)
from warptex.machine import memory_problem
from warptex.parallel import launch_ranges
from warptex.settings import (
    DEFAULT_COARSE_CACHE_BYTES,
    DEFAULT_JITTER,
    DEFAULT_PASSES,
    check_count,
    check_flag,
    check_settings,
    is_integer,
)
from warptex.thread_warnings import warn
from warptex.warp_runtime import device as default_device
from warptex.warp_runtime import init_warp

# Raised whenever the engine gives any voxel another result from the same inputs, so that
# brick stores written by an earlier engine are not reused. 2: shifted neighbour triples;
# 3: every candidate a set keeps is searched (only sets with non-default counts changed);
# 4: shifted triples never cross the margins of exemplars that do not tile.
ENGINE_VERSION = 4
_LEVELS = 3  # levels above the finest synthesized: section 5.1's l_start = L - 3
BLOCK = _k.BLOCK
_BLOCK_VOXELS = _k.BLOCK_VOXELS
_TRIPLE_BYTES = 3 * 4  # a cached voxel's triple of int32 pixel indices
# Blocks kept free at the ends of the biased 21-bit key fields for the work region around a
# request (its apron of dependencies, plus one block of neighbour lookups): the largest apron
# of the settings the engine takes fits (tests/test_synthesis.py holds them to it), so a key
# field never over- or underflows.
_KEY_MARGIN = 64
COORD_LIMIT = BLOCK * (KEY_BIAS - _KEY_MARGIN)  # finest voxels lie in [-COORD_LIMIT, COORD_LIMIT)
# Blocks whose halos are gathered at once: on the CPU few enough (256 * 8^3 voxels for
# N=5) that they are still cached when projected; a GPU wants many threads per launch.
_HALO_CHUNK = {"cpu": 256, "cuda": 8192}
# Finest voxels in the work region (request and apron) of one engine call: a larger request
# is synthesized in parts, one after another, so its working memory stays under about
# MAX_WORK_VOXELS * work_bytes_per_voxel(3) (4.7 GB, host or GPU, for RGB). A 1024^3
# surface's query batches (about 13M work voxels each for the bunny) stay whole.
MAX_WORK_VOXELS = 1 << 24
# Working memory per work voxel: 280 bytes for RGB, the peak memory growth of a 64 x 256 x
# 256 box (granite_64, 2 passes) over its 5.0M work voxels, and at most 6 more per feature
# channel beyond three (the halos and features gathered): a 56^3 box grew by 218-251 and
# 296-437 bytes a work voxel at 3 and 34 channels (BENCHMARKS.md, "Memory of a request").
# And 10 more per correction step beyond the default two (passes times sub-passes): a work
# voxel took 326 bytes at 8 passes, 405 at 4 passes of 8 sub-passes, 603 at 8 of 8
# (BENCHMARKS.md, "Memory of a request against its correction steps").
_WORK_BYTES_RGB = 280
_WORK_BYTES_PER_CHANNEL = 6
_WORK_BYTES_PER_STEP = 10
_DEFAULT_STEPS = DEFAULT_PASSES  # correction steps a level at the default passes of one sub-pass
# Host memory of a request beside the engine's, per requested voxel (its coordinates, keys,
# parts and triples), rounded up: a 256^3 box in two parts grew by 70 bytes a voxel more
# than one part's work.
REQUEST_BYTES_PER_VOXEL = 100
# And per key of its blocks grown by the apron ((2 apron + 1)^3 a block), which splitting
# it into parts sorts and keeps: scattered voxels, a block each, of which a box holds 512.
# Measured: 744-997 bytes a voxel in all for 200,000 and 1,000,000 scattered voxels, 27
# keys each, the engine's own work left out (BENCHMARKS.md, "Memory of a request").
DILATED_KEY_BYTES = 36
# A neighbour table is read from a dense grid over its blocks' bounding box where that grid
# has at most this many cells a block: 32 bytes of grid per 108 bytes of table.
_DENSE_CELLS_PER_BLOCK = 8
_FINEST_CANDIDATES_3D = 4  # "2 2D and 4 3D candidates at the finest level" (section 5.1)
_LOCAL = cell_offsets(BLOCK)


def work_bytes_per_voxel(channels: int = 3, steps: int = _DEFAULT_STEPS) -> int:
    """Working memory of the engine per finest work voxel, for exemplars of ``channels``
    feature channels (colors and any feature distance) and ``steps`` correction steps a
    level (passes times sub-passes)."""
    return (_WORK_BYTES_RGB + _WORK_BYTES_PER_CHANNEL * (max(channels, 3) - 3)
            + _WORK_BYTES_PER_STEP * (max(steps, _DEFAULT_STEPS) - _DEFAULT_STEPS))


def box_bytes(shape: tuple[int, int, int], apron_blocks: int = 1, channels: int = 3,
              work_cap: int = MAX_WORK_VOXELS, steps: int = _DEFAULT_STEPS) -> int:
    """About the memory that synthesizing a box of ``shape`` takes beside its colors: its
    request's host arrays and the engine's work on one part of it (the box and its apron,
    at most ``work_cap`` voxels, or one block's); ``apron_blocks`` is the engine's (one at
    the default passes), ``channels`` its feature channels, ``work_cap`` its parts' size
    (:func:`work_voxel_cap`) and ``steps`` its correction steps, as for
    :func:`request_bytes`."""
    reach = 2 * apron_blocks * BLOCK
    # The engine splits no part below one block, whose work may exceed a small machine's cap.
    work = min(max(work_cap, (BLOCK + reach) ** 3), math.prod(n + reach for n in shape))
    return (math.prod(shape) * REQUEST_BYTES_PER_VOXEL
            + work * work_bytes_per_voxel(channels, steps))


def request_bytes(ijk: np.ndarray, apron_blocks: int = 1, channels: int = 3,
                  work_cap: int = MAX_WORK_VOXELS, steps: int = _DEFAULT_STEPS) -> int:
    """About the memory that synthesizing voxels ``ijk`` (N, 3) takes beside their results:
    the request's host arrays, its blocks' keys grown by the apron, and the engine's work
    on one part of it (its bounding box grown by the apron, or each voxel's block and apron
    where they lie far apart, at most ``work_cap`` voxels, or one block's); ``apron_blocks``
    is the engine's (one at the default passes), ``channels`` its feature channels,
    ``work_cap`` its parts' size (:func:`work_voxel_cap`) and ``steps`` its correction steps
    a level (passes times sub-passes)."""
    if len(ijk) == 0:
        return 0
    reach = 2 * apron_blocks * BLOCK
    spread = ijk.max(axis=0) - ijk.min(axis=0) + 1 + reach
    # The work region is made of whole blocks: the blocks the voxels lie in, grown.
    blocks_spread = ijk.max(axis=0) // BLOCK - ijk.min(axis=0) // BLOCK + 1 + 2 * apron_blocks
    box = math.prod(int(s) * BLOCK for s in blocks_spread)  # Python ints: up to 2^69 voxels
    block = (BLOCK + reach) ** 3  # one block's work, which no part goes below
    work = min(max(work_cap, block), len(ijk) * block, box)
    blocks = min(len(ijk), math.prod(-(-int(s) // BLOCK) + 1 for s in spread))
    dilated = blocks * (2 * apron_blocks + 1) ** 3 * DILATED_KEY_BYTES
    return (len(ijk) * REQUEST_BYTES_PER_VOXEL + dilated
            + work * work_bytes_per_voxel(channels, steps))


def _check_request(ijk: np.ndarray, apron_blocks: int, channels: int, work_cap: int,
                   steps: int, result_bytes: int) -> None:
    """Refuse, before any work, a request of voxels ``ijk`` that with its results of
    ``result_bytes`` a voxel would not fit in this machine's memory, the engine working on
    parts of ``work_cap`` voxels with ``steps`` correction steps. Not asked of the brick
    store's batches, which are bounded (``store.BATCH_VOXELS``), as the machine's memory
    takes a file read."""
    problem = memory_problem(request_bytes(ijk, apron_blocks, channels, work_cap, steps)
                             + len(ijk) * result_bytes)
    if problem is not None:
        raise ValueError(f"a request of {len(ijk)} voxels {problem}; synthesize them in parts")


def work_voxel_cap(device: str, channels: int = 3, steps: int = _DEFAULT_STEPS) -> int:
    """Work voxels of one engine call on ``device`` for exemplars of ``channels`` feature
    channels and ``steps`` correction steps a level: ``MAX_WORK_VOXELS``, fewer where that
    many would take more than half of the GPU's memory (a 4 GB one) or, on the CPU, of what
    the process may have (:func:`~warptex.machine.physical_memory`: a small machine, a
    container, ``ulimit -v``), leaving the rest to the brick store, a renderer and other
    processes. Scattered points' requests reach the cap, which the brick store's batches
    are not checked against. Parts change no voxel (section 5.2)."""
    memory = _device_memory(device) if device.startswith("cuda") else _host_memory()
    if memory is None:
        return MAX_WORK_VOXELS
    return max(1, min(MAX_WORK_VOXELS,
                      memory // (2 * work_bytes_per_voxel(channels, steps))))


@cache
def _device_memory(device: str) -> int:
    return int(wp.get_device(device).total_memory)


@cache
def _host_memory() -> int | None:
    # Once a process: reading the system's and the cgroups' files takes 0.2 ms, more than
    # many a small request's work.
    return machine.physical_memory()


def work_voxels(shape: tuple[int, int, int], passes: int = DEFAULT_PASSES) -> int:
    """About how many voxel corrections synthesizing a box of ``shape`` takes, a measure of
    its time: at each level from the finest, the box grown by the apron its passes read
    (section 5.2), corrected ``passes`` times, then halved for the level above. The aprons
    grow with the passes, so a small box of many passes can take longer than a large one."""
    apron = BLOCK * default_apron_blocks(passes)
    sides = np.asarray(shape, np.int64)
    work = 0
    for _ in range(_LEVELS + 1):
        sides = sides + 2 * apron
        work += max(passes, 1) * int(np.prod(sides))
        sides = -(-sides // 2)
    return work


def check_voxels(ijk: np.ndarray) -> np.ndarray:
    """Voxel coordinates ``ijk`` as an (N, 3) int64 array, or a ValueError: they must be
    integers (a fraction names no voxel) within [-COORD_LIMIT, COORD_LIMIT), where block
    keys hold them without wrapping onto another voxel."""
    outside = f"voxel coordinates must lie within [-{COORD_LIMIT}, {COORD_LIMIT})"
    given = ijk
    try:
        ijk = np.asarray(ijk)
    except ValueError:  # NumPy's words name no argument
        raise ValueError("voxel coordinates must be an (N, 3) integer array, got rows of "
                         "other lengths") from None
    if (not isinstance(given, np.ndarray) and ijk.ndim == 2 and ijk.dtype.kind in "iu"
            and _any_bool(given)):
        raise ValueError("voxel coordinates must be integers, got booleans among them")
    if ijk.ndim != 2 or ijk.shape[1] != 3 or not np.issubdtype(ijk.dtype, np.integer):
        if _python_ints(given):  # beyond int64, which NumPy made objects or floats of
            raise ValueError(outside)
        raise ValueError(f"voxel coordinates must be an (N, 3) integer array, got "
                         f"{ijk.dtype} {ijk.shape}")
    if len(ijk) and (ijk.min() < -COORD_LIMIT or ijk.max() >= COORD_LIMIT):
        raise ValueError(outside)
    return ijk.astype(np.int64, copy=False)


def _any_bool(rows: object) -> bool:
    """Whether rows of numbers hold a bool, which NumPy makes 0 or 1 among integers."""
    return any(isinstance(v, bool | np.bool_) for row in rows for v in row)


def _python_ints(values: object) -> bool:
    """Whether ``values``, not a NumPy array, are rows of three Python ints."""
    if isinstance(values, np.ndarray):
        return False
    try:
        rows = np.asarray(values, dtype=object)
    except ValueError:  # ragged
        return False
    return (rows.ndim == 2 and rows.shape[1] == 3 and rows.size > 0
            and all(isinstance(v, Integral) and not isinstance(v, bool) for v in rows.flat))


def _three_ints(name: str, values) -> tuple[int, int, int]:
    """``values`` as three Python ints, or a ValueError naming ``name``: fractions are
    refused, not truncated onto another voxel."""
    items = tuple(values) if np.ndim(values) == 1 else ()
    if len(items) != 3 or not all(isinstance(v, Integral) and not isinstance(v, bool)
                                  for v in items):
        raise ValueError(f"{name} must be three ints, got {values!r}")
    return tuple(int(v) for v in items)


def _key_step(d: tuple[int, int, int]) -> int:
    """What adding block offset ``d`` adds to a packed key (fields never over- or
    underflow: requests stay ``_KEY_MARGIN`` blocks inside their biased 21 bits)."""
    return (d[0] << (2 * KEY_BITS)) + (d[1] << KEY_BITS) + d[2]


def _dilate(keys: np.ndarray, r: int) -> np.ndarray:
    """Sorted unique ``keys`` grown by ``r`` blocks in every direction: one axis at a
    time, each a merge of 2r + 1 shifted copies (sorted runs, which timsort merges)."""
    for axis in range(3):
        step = _key_step(tuple(int(a == axis) for a in range(3)))
        runs = np.concatenate([keys + o * step for o in range(-r, r + 1)])
        runs.sort(kind="stable")
        keys = distinct_sorted(runs)
    return keys


def _neighbor_table(keys: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """Slot of each of the 27 blocks around each block of sorted ``keys`` (x slowest),
    -1 where absent; ``blocks`` are their coordinates. A compact set (a box and its apron)
    is looked up in a dense grid over its bounding box, five times faster than searching;
    a sparse one (scattered queries) is searched."""
    offsets = np.indices((3, 3, 3)).reshape(3, -1).T - 1
    low = blocks.min(axis=0) - 1
    shape = [int(n) for n in blocks.max(axis=0) - low + 2]
    if shape[0] * shape[1] * shape[2] > _DENSE_CELLS_PER_BLOCK * len(keys):
        steps = [_key_step(d) for d in offsets]
        return np.stack([lookup(keys, keys + s) for s in steps], axis=1).astype(np.int32)
    strides = np.array([shape[1] * shape[2], shape[2], 1])
    cell = (blocks - low) @ strides
    grid = np.full(shape[0] * shape[1] * shape[2], -1, np.int32)
    grid[cell] = np.arange(len(keys), dtype=np.int32)
    return grid[cell[:, None] + offsets @ strides]


def _enclosed(need: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Blocks whose 27 blocks around (themselves included) are all present and wholly in
    the mask ``need`` (a byte per work voxel): a correction reads at most one block away,
    so spreading the mask from their voxels would mark nothing new, and inside a box that
    is most voxels (section 5.2's masks, at a fraction of the writes)."""
    full = need.reshape(-1, _BLOCK_VOXELS).all(axis=1)
    return np.all((table >= 0) & full[table], axis=1)


@dataclass
class _Level:
    """Final (corrected) triples in some blocks of one level, sorted by block key; only
    the voxels asked for are defined."""

    keys: np.ndarray
    triples: np.ndarray  # (M * 64, 3) int32


class _LevelCache:
    """Coarse-level cache (section 6.2): final triples of coarse voxels, kept by block
    with one bit per voxel, reused across requests. Values are position-determined, so
    hits never change a result."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.clear()

    def clear(self) -> None:
        # bit l of valid: voxel l of the block is cached
        self.keys, self.triples, self.valid = (np.zeros(0, np.int64), np.zeros((0, 3), np.int32),
                                               np.zeros(0, np.uint64))

    def find(self, keys: np.ndarray, flat: np.ndarray) -> np.ndarray:
        """Row in ``triples`` of each voxel ``flat`` (block * 64 + local) of the blocks
        ``keys``, -1 where not cached."""
        if len(self.keys) == 0:
            return np.full(len(flat), -1, np.int64)
        slot, local = self._slots(keys, flat)
        bits = self.valid[np.maximum(slot, 0)] >> local.astype(np.uint64)
        hit = (slot >= 0) & (bits & np.uint64(1) != 0)
        return np.where(hit, slot * _BLOCK_VOXELS + local, -1)

    def _slots(self, keys: np.ndarray, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cache slot (-1 where the block is not cached) and local index of each voxel
        ``flat`` (block * 64 + local) of the blocks ``keys``."""
        slot = lookup(self.keys, keys)[flat // _BLOCK_VOXELS]
        return slot, flat % _BLOCK_VOXELS

    def insert(self, keys: np.ndarray, flat: np.ndarray, triples: np.ndarray) -> None:
        """Keep ``triples`` of the uncached voxels ``flat`` (sorted) of the blocks ``keys``;
        starts over when full."""
        new = distinct_sorted(keys[flat // _BLOCK_VOXELS])
        if len(new) * _BLOCK_VOXELS * _TRIPLE_BYTES > self.max_bytes:
            return
        if (len(self.keys) + len(new)) * _BLOCK_VOXELS * _TRIPLE_BYTES > self.max_bytes:
            self.clear()
        fresh = new[lookup(self.keys, new) < 0]
        if len(fresh):
            keys_all = np.concatenate([self.keys, fresh])
            order = np.argsort(keys_all, kind="stable")
            blocks = np.concatenate([self.triples.reshape(-1, _BLOCK_VOXELS, 3),
                                     np.zeros((len(fresh), _BLOCK_VOXELS, 3), np.int32)])
            valid = np.concatenate([self.valid, np.zeros(len(fresh), np.uint64)])
            # One assignment, which Python does not stop half way (Ctrl-C is raised at
            # calls and loops): the three never disagree, whatever stops the request.
            self.keys, self.triples, self.valid = (keys_all[order],
                                                   blocks[order].reshape(-1, 3), valid[order])
        slot, local = self._slots(keys, flat)
        self.triples[slot * _BLOCK_VOXELS + local] = triples
        # The bits last: a stop before them leaves voxels uncached, never cached wrong.
        # ``flat`` is sorted, so each block's voxels lie together: one OR per block.
        starts = run_starts(slot)
        self.valid[slot[starts]] |= np.bitwise_or.reduceat(
            np.uint64(1) << local.astype(np.uint64), starts)


def engine_device(device: str | None) -> str:
    """The Warp device an engine asked for ``device`` (None: :func:`warptex.device`) runs
    on, resolved once: "cuda" names whichever GPU is current on the calling thread, and
    every array and launch of an engine stays on one GPU ("cuda:0")."""
    init_warp()
    if device is None:  # WARPTEX_DEVICE's errors name it, not an argument never given
        return str(wp.get_device(default_device()))
    try:
        return str(wp.get_device(device))
    except (ValueError, RuntimeError) as error:  # Warp's words name no argument
        raise ValueError(f"device must be a Warp device such as 'cpu' or 'cuda:0', got "
                         f"{device!r} ({error})") from None


def not_pickled(what: str) -> str:
    """Why ``what`` (an engine, or a texture holding one) is not pickled or copied: Warp's
    arrays and the locks it holds are the process's, where pickle failed inside ctypes."""
    return (f"{what} holds Warp arrays of this process and is not pickled or copied: make "
            "one in each process from its exemplar or CandidateSet (which pickles); the "
            "same settings give the same voxels")


class Synthesizer:
    """Colors of any subset of an unbounded solid texture (Dong 2008, section 5).

    Voxel coordinates are integers over all of Z^3 at the finest level L; level l voxel v
    covers finest voxels ``2**(L-l) * v ...``. Synthesis starts ``levels`` levels above the
    finest (at the candidates' coarsest where they hold fewer) with a warped tiling of the
    candidate slab and runs ``passes`` correction passes of ``subpasses`` interleaved
    sub-passes per level. The default ``levels=3`` is section 5.1's start three levels above
    the finest (l_start = L - 3); section 5.2's "3 last levels" could also be read as
    ``levels=2``, which repeats more (BENCHMARKS.md). ``shifted_tiles`` shifts each tile of
    the slab by its own hashed offset, so that structured exemplars do not repeat every
    exemplar width, at some cost in their neighbourhood energy (BENCHMARKS.md, "Exemplars
    that do not tile"). The ``seed`` acts through the jitter's warp and the tiles' shifts
    only: without either every seed gives the same solid (warned of), and a jitter under
    about 0.1 moves few voxels.
    """

    def __init__(
        self,
        candidates: CandidateSet,
        seed: int = 0,
        jitter: float = DEFAULT_JITTER,
        *,
        levels: int = _LEVELS,
        passes: int = DEFAULT_PASSES,
        subpasses: int = 1,
        device: str | None = None,
        coarse_cache_bytes: int = DEFAULT_COARSE_CACHE_BYTES,
        shifted_tiles: bool = False,
    ) -> None:
        if not isinstance(candidates, CandidateSet):
            raise TypeError(f"candidates must be a CandidateSet (warptex.precompute makes one), "
                            f"got {type(candidates).__name__}")
        if not is_integer(subpasses) or subpasses not in (1, 8):
            raise ValueError(f"subpasses must be 1 or 8, got {subpasses}")
        check_settings(jitter, passes, seed)
        levels = check_count("levels", levels)
        coarse_cache_bytes = check_count("coarse_cache_bytes", coarse_cache_bytes)
        self.candidates = candidates
        self.seed = int(seed)
        self.jitter = float(jitter)
        self.shifted_tiles = check_flag("shifted_tiles", shifted_tiles)
        if self.seed != 0 and self.jitter_steps == 0 and not self.shifted_tiles:
            none = ("there is no jitter" if self.jitter == 0
                    else f"a jitter of {self.jitter:g} is taken as 0 (at most 1/512)")
            warn(f"seed {self.seed} gives the same solid as seed 0: the seed acts through the "
                 f"jitter's random warp and the tiles' shifts, and {none}, with no tiles "
                 "shifted", stacklevel=2)
        self.passes = int(passes)
        self.subpasses = int(subpasses)
        self.device = engine_device(device)
        self.finest = candidates.num_levels - 1
        self.start = max(0, self.finest - int(levels))
        half = int(candidates.params["neighborhood"]) // 2
        if half > BLOCK:
            raise ValueError(f"neighbourhoods of more than {2 * BLOCK + 1} voxels are not "
                             f"supported (the candidates use {2 * half + 1}): a kernel reads "
                             f"voxels at most {BLOCK} away through its block's neighbours")
        self._features = int(candidates.sources[0][0].feat.shape[2])
        check_feature_channels(self._features, 2 * half + 1)
        self._apron = apron_blocks(half, self.passes, self.subpasses)
        self._steps = len(correction_steps(self.passes, self.subpasses))
        reads = np.argwhere(neighborhood_shape(half)) - half
        reads = reads[np.abs(reads).sum(axis=1) > 0]
        self._shape = wp.array(reads.astype(np.int32), dtype=wp.vec3i, device=self.device)
        self._tables = {lv: self._level_tables(lv) for lv in range(self.start, self.finest + 1)}
        self._cache = {lv: _LevelCache(coarse_cache_bytes) for lv in range(self.start, self.finest)}
        self._lock = threading.Lock()
        self.voxels_synthesized = {lv: 0 for lv in range(self.start, self.finest + 1)}

    # -- public API -------------------------------------------------------------------

    def triples(self, ijk: np.ndarray) -> np.ndarray:
        """Finest-level coordinate triples (N, 3, 2) of voxels ``ijk`` (N, 3) ints.

        Entry ``[n, k]`` is the (row, column) of the pixel of axis k's exemplar. A request
        that would not fit in memory is a ValueError, before any work.
        """
        ijk = check_voxels(ijk)
        # Its triples, and the int64 rows, columns and their stack on the way.
        _check_request(ijk, self._apron, self._features, self._work_cap(), self._steps, 136)
        pix = self._pixel_triples(ijk)
        widths = np.array([self._tables[self.finest].width[k] for k in range(3)])
        return np.stack([pix // widths, pix % widths], axis=-1).astype(np.int32)

    def __getstate__(self) -> NoReturn:
        raise TypeError(not_pickled("a Synthesizer"))

    def voxels(self, ijk: np.ndarray) -> np.ndarray:
        """Colors (N, C) float32 of voxels ``ijk`` (N, 3): the average of three exemplar
        colors (section 5.1). A request that would not fit in memory is a ValueError, before
        any work."""
        ijk = check_voxels(ijk)
        _check_request(ijk, self._apron, self._features, self._work_cap(), self._steps,
                       4 * self.candidates.channels)
        return self.colors_of(self._pixel_triples(ijk))

    def box(self, origin: tuple[int, int, int], shape: tuple[int, int, int]) -> np.ndarray:
        """Colors of a box of voxels, (X, Y, Z, C): axis 0 along x, 1 along y, 2 along z."""
        origin = _three_ints("origin", origin)
        shape = _three_ints("shape", shape)
        if min(shape) < 0:
            raise ValueError(f"shape must be three non-negative ints, got {shape}")
        if not all(o >= -COORD_LIMIT and o + n <= COORD_LIMIT
                   for o, n in zip(origin, shape, strict=True)):  # checked before any array
            raise ValueError(f"a box at origin {origin} of shape {shape} leaves the voxel "
                             f"coordinates' range [-{COORD_LIMIT}, {COORD_LIMIT})")
        need = (box_bytes(shape, self._apron, self._features, self._work_cap(), self._steps)
                + 4 * self.candidates.channels * math.prod(shape))
        problem = memory_problem(need)
        if problem is not None:  # before allocating: too large a box would end in swapping
            raise ValueError(f"a box of shape {shape} {problem}; synthesize it in parts")
        grid = np.indices(shape).reshape(3, -1).T + np.asarray(origin, np.int64)
        colors = self.colors_of(self._pixel_triples(check_voxels(grid)))
        return colors.reshape(*shape, self.candidates.channels)

    @property
    def jitter_steps(self) -> int:
        """The jitter as the engine takes it: in steps of 1/256, the warp's integer
        amplitudes (section 5.1, "Jitter"); jitters of one step are one texture."""
        return round(self.jitter * 256)

    def colors_of(self, pixels: np.ndarray) -> np.ndarray:
        """Average the three exemplar colors of finest-level triples of pixel indices, (N, 3)
        integers as :meth:`pixel_triples` gives them."""
        cs = self.candidates
        cols = [np.asarray(cs.colors[cs.axis_source[k]], np.float32).reshape(-1, cs.channels)
                for k in range(3)]
        pixels = np.asarray(pixels)
        if (pixels.ndim != 2 or pixels.shape[1] != 3
                or not np.issubdtype(pixels.dtype, np.integer)):
            raise ValueError(f"pixels must be an (N, 3) integer array of pixel triples, got "
                             f"{pixels.dtype} of shape {pixels.shape}")
        if len(pixels) and any(not 0 <= pixels[:, k].min() <= pixels[:, k].max() < len(c)
                               for k, c in enumerate(cols)):
            raise ValueError("pixels must index each axis' exemplar, from 0 to its pixel "
                             "count less one")
        # np.take gathers rows about 4x faster than indexing does.
        out = np.take(cols[0], pixels[:, 0], axis=0)
        out += np.take(cols[1], pixels[:, 1], axis=0)
        out += np.take(cols[2], pixels[:, 2], axis=0)
        out /= np.float32(3.0)
        return out

    def pixel_triples(self, ijk: np.ndarray) -> np.ndarray:
        """Finest-level triples (N, 3) int32 of voxels ``ijk`` (N, 3) ints as flat pixel
        indices: entry ``[n, k]`` is ``row * width + column`` in axis k's exemplar, what the
        brick store keeps (section 6.2). Unlike :meth:`voxels` and :meth:`triples`, no
        request is refused up front (the brick store's batches are bounded); its engine
        calls stay within :func:`work_voxel_cap` all the same."""
        return self._pixel_triples(check_voxels(ijk))

    # -- orchestration ----------------------------------------------------------------

    def _pixel_triples(self, ijk: np.ndarray) -> np.ndarray:
        """:meth:`pixel_triples` of voxels ``ijk`` that :func:`check_voxels` gave."""
        if len(ijk) == 0:
            return np.zeros((0, 3), np.int32)
        with self._lock:  # the finest level is never cached: just the voxels asked for
            return self._in_parts(ijk)

    def _in_parts(self, ijk: np.ndarray) -> np.ndarray:
        """Finest pixel triples of int64 voxels ``ijk``, their blocks synthesized in parts
        of at most :func:`work_voxel_cap` work voxels. A voxel's triple does not depend on what
        else is requested (section 5.2), so the parts give what one call would."""
        keys = pack(ijk // BLOCK)
        local = local_index(ijk, BLOCK)
        uniq = unique(keys)
        parts = self._parts(uniq)
        if len(parts) == 1:  # the common case, without a copy of the request per part
            return self._synthesize(self.finest, uniq, keys, local, parts[0][1])
        part_of_block = np.empty(len(uniq), np.int64)
        for n, (part_keys, _) in enumerate(parts):
            part_of_block[lookup(uniq, part_keys)] = n
        part = part_of_block[lookup_runs(uniq, keys)]
        out = np.empty((len(ijk), 3), np.int32)
        for n, (part_keys, work) in enumerate(parts):
            rows = np.flatnonzero(part == n)
            out[rows] = self._synthesize(self.finest, part_keys, keys[rows], local[rows], work)
        return out

    def _parts(self, keys: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """The sorted block ``keys`` in parts, each with its work region (its blocks grown
        by the apron) of at most :func:`work_voxel_cap` finest voxels unless a single block's
        is larger: halved across the longest side of their bounding box, so that parts stay
        compact and their aprons small."""
        work = _dilate(keys, self._apron)
        if len(work) * _BLOCK_VOXELS <= self._work_cap() or len(keys) == 1:
            return [(keys, work)]
        blocks = unpack(keys)
        low, high = blocks.min(axis=0), blocks.max(axis=0)
        axis = int(np.argmax(high - low))
        below = blocks[:, axis] < (low[axis] + high[axis] + 1) // 2
        return self._parts(keys[below]) + self._parts(keys[~below])

    def _work_cap(self) -> int:
        """Work voxels of one engine call here (:func:`work_voxel_cap`): what requests are
        split into, and estimated by."""
        return work_voxel_cap(self.device, self._features, self._steps)

    def _final(self, level: int, keys: np.ndarray, flat: np.ndarray) -> _Level:
        """Corrected triples at ``level`` of the voxels ``flat`` (block * 64 + local,
        sorted) of the blocks ``keys``: from the coarse cache where it holds them, the
        others synthesized in one call."""
        out = _Level(keys, np.zeros((len(keys) * _BLOCK_VOXELS, 3), np.int32))
        cache = self._cache[level]
        found = cache.find(keys, flat)
        hit = found >= 0
        if hit.any():
            out.triples[flat[hit]] = cache.triples[found[hit]]
        missing = flat[~hit]
        if len(missing):
            voxel_keys = keys[missing // _BLOCK_VOXELS]
            out.triples[missing] = self._synthesize(level, distinct_sorted(voxel_keys),
                                                    voxel_keys, missing % _BLOCK_VOXELS)
            cache.insert(keys, missing, out.triples[missing])
        return out

    def _synthesize(self, level: int, keys: np.ndarray, voxel_keys: np.ndarray,
                    local: np.ndarray, work: np.ndarray | None = None) -> np.ndarray:
        """Triples (N, 3) of the desired voxels of ``level``, given by their block's key
        and their index in it, which lie in the blocks ``keys``: synthesized on a work
        region padded by the apron (``work``, when the caller has it already).

        Section 5.2: each correction step visits just the voxels whose value later steps
        read on the way to the desired ones, and the parent level is asked for just the
        parents of the voxels that the first step reads.
        """
        work = _dilate(keys, self._apron) if work is None else work
        coords = unpack(work).astype(np.int32)
        dev = self.device
        t = self._tables[level]
        nvox = len(work) * _BLOCK_VOXELS
        coords_wp = wp.array(coords, dtype=wp.vec3i, device=dev)
        table = _neighbor_table(work, coords)
        nbr = wp.array(table, dtype=wp.int32, device=dev)
        flat = lookup_runs(work, voxel_keys) * _BLOCK_VOXELS + local
        active, read, read_host = self._dependency_lists(nbr, table, coords, flat)
        # Zeros (pixel 0) in blocks left out of the upsampling, so whole-array kernels
        # such as the features read valid pixels everywhere.
        triples = wp.zeros(nvox, dtype=wp.vec3i, device=dev)
        if level == self.start:
            launch_ranges(_k.initialize, 0, nvox,
                          [coords_wp, t, self.seed, self.jitter_steps, int(self.shifted_tiles)],
                          [triples], device=dev)
        else:
            read_blocks = np.flatnonzero(read_host.reshape(-1, _BLOCK_VOXELS).any(axis=1))
            parent = self._final(level - 1, *self._parents(coords_wp, coords, read,
                                                           read_blocks))
            parent_slot = np.full(len(coords), -1, np.int32)
            parent_slot[read_blocks] = lookup(parent.keys, pack(coords[read_blocks] >> 1))
            pt = self._tables[level - 1]
            launch_ranges(
                _k.upsample,
                0,
                nvox,
                [
                    coords_wp,
                    wp.array(parent_slot, dtype=wp.int32, device=dev),
                    wp.array(parent.triples, dtype=wp.vec3i, device=dev),
                    pt.width,
                    t,
                ],
                [triples],
                device=dev,
            )
        self._correct(active, nbr, triples, t)
        # The mask only grows as the steps are undone, so the first step of each parity
        # class lists every voxel of that class that any step corrects.
        first_of_class: dict[int, int] = {}
        for step, listed in zip(correction_steps(self.passes, self.subpasses), active,
                                strict=True):
            first_of_class.setdefault(step, len(listed))
        self.voxels_synthesized[level] += sum(first_of_class.values())
        return np.take(triples.numpy(), flat, axis=0)

    def _parents(self, coords_wp: wp.array, coords: np.ndarray, read: wp.array,
                 read_blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Blocks (sorted keys) and voxels (flat, sorted) one level up holding the
        parents of the voxels ``read`` marks, which lie in the blocks ``read_blocks`` of
        ``coords``: block c's parents lie in block c >> 1."""
        dev = self.device
        keys, slot = np.unique(pack(coords[read_blocks] >> 1), return_inverse=True)
        parent_block = np.full(len(coords), -1, np.int32)
        parent_block[read_blocks] = slot
        parents = wp.zeros(len(keys) * _BLOCK_VOXELS, dtype=wp.uint8, device=dev)
        launch_ranges(_k.mark_parents, 0, read.shape[0],
                      [read, coords_wp, wp.array(parent_block, dtype=wp.int32, device=dev)],
                      [parents], device=dev)
        return keys, np.flatnonzero(parents.numpy())

    def _dependency_lists(self, nbr: wp.array, table: np.ndarray, coords: np.ndarray,
                          desired: np.ndarray) -> tuple[list[np.ndarray], wp.array, np.ndarray]:
        """Section 5.2, ComputeMask, voxel-exact within one level: the voxels each
        correction step corrects (flat work indices, sorted) and the mask (one byte per
        work voxel) of the voxels the first step reads, on the device and on the host,
        undoing the steps from last to first. ``table`` is ``nbr`` on the host."""
        dev = self.device
        nvox = len(coords) * _BLOCK_VOXELS
        need = np.zeros(nvox, np.uint8)
        need[desired] = 1
        need_wp = wp.array(need, dtype=wp.uint8, device=dev)
        steps = correction_steps(self.passes, self.subpasses)
        active: list[np.ndarray] = []
        for step in reversed(steps):
            listed = np.flatnonzero(need).astype(np.int32)
            if step >= 0:
                world = coords[listed // _BLOCK_VOXELS] * BLOCK + _LOCAL[listed % _BLOCK_VOXELS]
                listed = listed[(world & 1) @ np.array([1, 2, 4]) == step]
            active.append(listed)
            spreading = listed[~_enclosed(need, table)[listed // _BLOCK_VOXELS]]
            launch_ranges(_k.spread_need, 0, len(spreading),
                          [wp.array(spreading, dtype=wp.int32, device=dev), nbr, self._shape],
                          [need_wp], device=dev)
            need = need_wp.numpy()
        return active[::-1], need_wp, need

    def _correct(self, active: list[np.ndarray], nbr: wp.array, triples: wp.array,
                 t: _k.LevelTables) -> None:
        """Correction passes (section 5.1): step n corrects the voxels ``active[n]``."""
        dev = self.device
        nvox = triples.shape[0]
        feats = wp.empty(nvox * t.nfeat, dtype=wp.float32, device=dev)
        # Uninitialized: a step reads only the projections of the voxels it listed.
        qproj = wp.empty(nvox * 3, dtype=_k.appearance_vector, device=dev)
        other = wp.empty_like(triples)
        src, dst = triples, other
        for listed in active:
            voxels = wp.array(listed, dtype=wp.int32, device=dev)
            launch_ranges(_k.voxel_features, 0, nvox, [src, t], [feats], device=dev)
            wp.copy(dst, src)
            self._correct_step(listed, voxels, nbr, src, feats, t, qproj, dst)
            src, dst = dst, src
        if src is not triples:
            wp.copy(triples, src)

    def _correct_step(self, listed: np.ndarray, voxels: wp.array, nbr: wp.array,
                      src: wp.array, feats: wp.array, t: _k.LevelTables, qproj: wp.array,
                      dst: wp.array) -> None:
        """One correction step of the voxels ``listed`` (sorted): their blocks are gathered
        with halos a chunk of blocks at a time, projected and corrected while the chunk
        is still in the cache; chunks also bound the halos' memory."""
        dev = self.device
        chunk = _HALO_CHUNK["cpu" if wp.get_device(dev).is_cpu else "cuda"]
        block = listed // _BLOCK_VOXELS
        starts = run_starts(block)  # listed voxels of each block (``listed`` is sorted)
        blocks = block[starts]
        halo_of = np.full(nbr.shape[0], -1, np.int32)
        halo_of[blocks] = np.arange(len(blocks)) % chunk
        side = BLOCK + 2 * t.half  # of a halo block (the kernels' halo_side)
        rows = side * side  # gathered per halo block, one thread each
        size = min(len(blocks), chunk) * rows * side
        halos = wp.empty(size * t.nfeat, dtype=wp.float32, device=dev)
        halo_src = wp.empty(size, dtype=wp.vec3i, device=dev)
        blocks_wp = wp.array(blocks, dtype=wp.int32, device=dev)
        halo_wp = wp.array(halo_of, dtype=wp.int32, device=dev)
        starts = [*starts.tolist(), len(listed)]
        for lo in range(0, len(blocks), chunk):
            hi = min(lo + chunk, len(blocks))
            launch_ranges(_k.gather_halos, lo * rows, hi * rows,
                          [lo, blocks_wp, nbr, src, feats, t], [halos, halo_src], device=dev)
            launch_ranges(_k.project_neighborhoods, starts[lo], starts[hi],
                          [voxels, halo_wp, halos, t], [qproj], device=dev)
            launch_ranges(_k.correct, starts[lo], starts[hi],
                          [voxels, halo_wp, halo_src, qproj, t], [dst], device=dev)

    def _level_tables(self, level: int) -> _k.LevelTables:
        """Upload one level's exemplar data; shared sources are stored once."""
        cs = self.candidates
        dev = self.device
        finest = level == cs.num_levels - 1
        sources = cs.sources[level]
        roles = cs.roles[level]
        n = int(cs.params["neighborhood"])
        t = _k.LevelTables()
        sizes = [sources[cs.axis_source[k]].size for k in range(3)]
        t.height = wp.vec3i(*[s[0] for s in sizes])
        t.width = wp.vec3i(*[s[1] for s in sizes])
        t.half = n // 2
        t.nfeat = int(sources[0].feat.shape[2])
        t.shift = wp.vec3i(*[sources[cs.axis_source[k]].shift for k in range(3)])
        t.margin_rows = wp.vec3i(*[sources[cs.axis_source[k]].margins[0] for k in range(3)])
        t.margin_cols = wp.vec3i(*[sources[cs.axis_source[k]].margins[1] for k in range(3)])
        # All the 2D candidates the candidate set keeps (its candidates_2d, or _finest), and
        # its 3D candidates, but only the paper's 4 of them at the finest level (section 5.1).
        t.k2 = int(sources[0].cand2d.shape[1])
        t.k3 = int(roles[0].cand.shape[1])
        if finest:
            t.k3 = min(t.k3, _FINEST_CANDIDATES_3D)

        def upload(arrays: list[np.ndarray], per_axis: list[int], dtype=wp.int32) -> tuple:
            """Concatenate per-source arrays; offsets count elements of ``dtype``."""
            rows = [a.reshape(-1) if dtype is wp.int32 else a for a in arrays]
            scalar = getattr(dtype, "_wp_scalar_type_", dtype)
            starts = np.cumsum([0] + [len(r) for r in rows])[:-1]
            return (
                wp.vec3i(*[int(starts[j]) for j in per_axis]),
                wp.array(np.concatenate(rows).astype(wp.dtype_to_numpy(scalar)), dtype=dtype,
                         device=dev),
            )

        def padded(a: np.ndarray) -> np.ndarray:
            """Rows of appearance vectors: unused dimensions are zero."""
            out = np.zeros((a.shape[0], _k.MAX_DIMS), np.int32)
            out[:, : a.shape[1]] = a
            return out

        src_of_axis = list(cs.axis_source)
        role_of_axis = [cs.role_of_axis(k) for k in range(3)]
        t.feat_off, t.feat = upload([s.feat for s in sources], src_of_axis)
        vec = _k.appearance_vector
        rows = [padded(s.basis.T) for s in sources]
        t.basis_off, t.basis = upload(rows, src_of_axis, _k.basis_row)
        t.proj_off, t.proj = upload([padded(s.proj) for s in sources], src_of_axis, vec)
        t.cand2d_off, t.cand2d = upload([s.cand2d for s in sources], src_of_axis)
        t.cand2d_stride = int(sources[0].cand2d.shape[1])
        t.cand3d_off, t.cand3d = upload([r.cand for r in roles], role_of_axis)
        t.cand3d_stride = int(roles[0].cand.shape[1])
        t.count3d_off, t.count3d = upload([r.count for r in roles], role_of_axis)
        return t
