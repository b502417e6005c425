"""Side-by-side comparisons of solid texture methods on one exemplar, or one per axis
(Dong 2008, 6.3-6.4; Kopf 2007). Each method runs in a fresh process so its time and peak
memory are its own; :class:`Setup` holds what they all run with, :func:`compare` runs them
and :func:`write_report` writes the sheet and tables.

Methods: ``lazy`` (this project), ``kopf`` (Kopf et al. 2007 global optimization, plain
weighted averages), ``kopf-meanshift`` (the same with its mean-shift clustering, section 4.1),
``tiled`` (a 64^3 block of the lazy engine's texture, or its whole volume when smaller,
repeated, the usual practice of Dong 2008 Fig. 11, which repeats a periodic block: above 64
voxels these copies also meet at seams),
and three
references that are no solid texture: ``extrude`` (the z axis' exemplar stacked along z),
``noise`` (i.i.d. exemplar pixels) and ``flat`` (the exemplars' mean color everywhere, which
shows what the neighbourhood energy rewards, ``warptex.metrics``).

Each axis may have an exemplar of its own (Kopf 2007, section 6.2; Dong 2008, section 4), as
wood shows rings across its grain and streaks along it: the methods that synthesize read all
three, and the slices across an axis are measured against that axis' exemplar.

Timing: the median of ``repeats`` wall-clock runs per method (one by default), in a fresh
process, its Warp kernels compiled by a small run first. Kopf's seconds include its PCA and
search structures; the lazy engine's pre-computation of candidates (Dong 2008, section 4) is
computed afresh by the ``lazy`` method, not read from the cache, and timed apart
(``precompute_seconds``), as the paper reports both; ``tiled`` reads the same candidates from
the cache (computing them there when ``lazy`` is not compared).
"""

from __future__ import annotations

import contextlib
import functools
import json
import multiprocessing
import multiprocessing.queues
import pickle
import queue
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import KW_ONLY, asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from tqdm import std
from tqdm.auto import tqdm

from warptex import metrics
from warptex.archive import file_problem, iso_date, one_file_twice, write_together
from warptex.exemplar import (
    AlphaDropped,
    Exemplar,
    ExemplarError,
    axis_triple,
    check_same_channels,
    srgb_encoded,
)
from warptex.machine import PeakMemory, map_large_blocks
from warptex.parallel import in_child_process
from warptex.settings import (
    DEFAULT_JITTER,
    DEFAULT_PASSES,
    check_count,
    check_file_name,
    check_flag,
    check_max_size,
    check_settings,
    check_tileable,
    tileable_word,
)
from warptex.srgb import linear_to_srgb, reencoded
from warptex.thread_warnings import captured

REPORT_FILES = ("sheet.png", "table.md", "table.json")  # what write_report writes
# Of table.json; 2: format, axes, passes, exemplar max size and digest; 3: pre-computation
# seconds, device memory, the settings of the methods and measures, more versions; 4: the
# exemplar of each axis, the lazy engine's jitter and shifted tiles as run; 5: repetition
# counts peaks of the autocorrelation only; 6: tiled's pre-computation seconds are null (it
# reads the candidates that lazy computed).
TABLE_FORMAT = 6
TILE = 64  # edge of the block that `tiled` repeats
_CUBE_SPP = 16
METHODS = ("lazy", "kopf", "kopf-meanshift", "tiled", "extrude", "noise", "flat")
# What each method is, as the command's help says it.
METHOD_NOTES = {
    "lazy": "this project's lazy synthesis (Dong 2008)",
    "kopf": "Kopf et al. 2007 global optimization of a periodic volume",
    "kopf-meanshift": "kopf with its mean-shift clustering (its section 4.1)",
    "tiled": f"a block of the lazy engine's volume, {TILE}^3 or the whole volume if smaller, "
             f"repeated, the usual practice (Dong 2008 Fig. 11); up to {TILE} voxels (the "
             "default --size) it is lazy's volume itself, told apart by the repetition score "
             "only",
    "extrude": "the z axis' exemplar stacked along z",
    "noise": "i.i.d. exemplar pixels",
    "flat": "the exemplars' mean color everywhere",
}
_LAZY = ("lazy", "tiled")  # the methods that run the lazy engine
_KOPF = ("kopf", "kopf-meanshift")
LARGE = 256  # least edge of the slice the repetition score looks at
MIN_SIZE = 8  # the measures read 5 x 5 patches of slices every 2 voxels
# What table.json says of how the numbers were taken.
TIMING = ("seconds: the median of the wall-clock runs per method in seconds_runs (as many "
          "as run.repeats), in a fresh process, Warp kernels compiled first; Kopf's include "
          "its PCA and search structures; the lazy engine's "
          "pre-computation of candidates, computed afresh, is timed apart (precompute_seconds; "
          "tiled reads them from the cache)")
MEMORY = ("peak_mib: rise of the process's resident host memory during the timed runs "
          "(the lazy engine's pre-computation, before them, not included); "
          "device_peak_mib: high-water mark of Warp's CUDA memory pool in the method's "
          "process (pre-computation and the kernels' first run included), null on the CPU")


@dataclass
class MethodResult:
    """Per-axis scores of one method (axis order x, y, z) and what it cost."""

    method: str
    energy: list[float]
    completeness: list[float]
    swd: list[float]
    histogram: list[float]
    repetition: float
    seconds: float  # the median of seconds_runs
    peak_mib: float
    notes: str = ""
    seconds_runs: list[float] = field(default_factory=list)
    device: str = "cpu"  # where the method computed: the lazy engine's device, else the CPU
    precompute_seconds: float | None = None  # the lazy engine's candidates, timed apart
    device_peak_mib: float | None = None  # Warp's CUDA memory pool, where the engine ran
    # The middle slices across x, y and z, as the sheet shows them; the repetition score's
    # large slice is taken at the middle z too.
    slices: list[np.ndarray] = field(default_factory=list, repr=False)
    render: np.ndarray | None = field(default=None, repr=False)


# The exemplars of the x, y and z axes; one Exemplar where axes show the same image.
Axes = tuple[Exemplar, Exemplar, Exemplar]


@dataclass(frozen=True)
class Setup:
    """What every method of a comparison runs and is measured with: the exemplar file of the
    x axis and, where given, of y and z (:meth:`paths`); the volume's edge; the seed of every
    randomized method; the lazy engine's correction passes, jitter and shifted tiles
    (``lazy`` and ``tiled``; :class:`warptex.synthesis.Synthesizer`); the larger side the
    exemplars are shrunk to when loaded and their feature-distance channel, automatic or
    from a mask of the one exemplar (``Exemplar.load``; lazy synthesis and Kopf match it,
    the measures take colors); and whether their opposite
    edges are continued (:meth:`Exemplar.seams`), by the methods that synthesize and in the
    measures alike. The settings are checked as it is made (a SettingError, TypeError or
    ValueError naming the field), the files when :meth:`exemplars` first reads them.

    The images read travel with it to each method's process, so every method sees the same
    exemplars; a file changed meanwhile is refused (the lazy cube's plugin reads it again).
    A Setup made anew (``dataclasses.replace`` too) reads the files afresh."""

    exemplar: Path
    size: int = 64
    _: KW_ONLY
    seed: int = 0
    passes: int = DEFAULT_PASSES
    jitter: float = DEFAULT_JITTER
    shifted_tiles: bool = False
    max_size: int | None = None
    tileable: bool | str = "auto"
    feature_distance: bool = False
    feature_mask: Path | None = None
    ey: Path | None = None
    ez: Path | None = None
    _axes: Axes | None = field(default=None, init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        check_settings(jitter=self.jitter, passes=self.passes, seed=self.seed)
        check_max_size(self.max_size)
        # Plain Python values, as table.json writes them (a NumPy integer would not be).
        checked = {"size": check_count("size", self.size, low=MIN_SIZE),
                   "seed": int(self.seed), "passes": int(self.passes),
                   "jitter": float(self.jitter),
                   "max_size": None if self.max_size is None else int(self.max_size),
                   "tileable": check_tileable(self.tileable),
                   "shifted_tiles": check_flag("shifted_tiles", self.shifted_tiles),
                   "feature_distance": check_flag("feature_distance", self.feature_distance),
                   "exemplar": check_file_name("exemplar", self.exemplar)}
        for name in ("feature_mask", "ey", "ez"):
            value = getattr(self, name)
            checked[name] = None if value is None else check_file_name(name, value)
        if checked["feature_mask"] is not None:
            if checked["feature_distance"]:
                raise ValueError("feature_mask and feature_distance exclude each other: the "
                                 "mask marks the features the distance is taken from")
            if checked["ey"] is not None or checked["ez"] is not None:
                raise ValueError("feature_mask marks one exemplar; with ey/ez use "
                                 "feature_distance")
        for name, value in checked.items():
            object.__setattr__(self, name, value)

    def paths(self) -> tuple[Path, Path, Path]:
        """The exemplar files of the x, y and z axes (:func:`warptex.exemplar.axis_triple`)."""
        return axis_triple(self.exemplar, self.ey, self.ez)

    def load_options(self) -> dict:
        """How each exemplar file is read (``Exemplar.load``'s keywords)."""
        return {"max_size": self.max_size, "feature_mask": self.feature_mask,
                "feature_distance": "auto" if self.feature_distance else False}

    def exemplars(self) -> Axes:
        """The exemplars of the x, y and z axes, read on the first call, each file once with
        ``max_size``; an image given under two names is one Exemplar. An ExemplarError (a
        ValueError) names the files whose channels or color encodings differ, which one
        volume cannot mix."""
        if self._axes is None:
            object.__setattr__(self, "_axes", _read_axes(self))
        return self._axes


@dataclass
class Comparison:
    """What :func:`compare` returns and :func:`write_report` writes: the :class:`Setup` and
    one result per method, in the order asked."""

    setup: Setup
    results: list[MethodResult]


def _read_axes(setup: Setup) -> Axes:
    """:meth:`Setup.exemplars`, read."""
    paths = setup.paths()
    files = {}
    for path in dict.fromkeys(paths):
        with captured() as said:
            files[path] = Exemplar.load(path, **setup.load_options())
        for warning in said:  # the loader's advice names an option compare does not have
            text = (f"{path}: alpha channel dropped (compare measures colors only)"
                    if issubclass(warning.category, AlphaDropped) else warning.message)
            warnings.warn(text, warning.category, stacklevel=3)  # the caller of exemplars()
    for path, exemplar in files.items():
        if exemplar.constant:  # its warning said so already
            raise ExemplarError(f"{path}: image is constant: the measures are in units of "
                                "its variance, which it has none of")
    read = [files[path] for path in paths]
    check_same_channels(read)  # before merging, so that errors name the files given
    srgb_encoded(read, raw=None)
    # The digest is of the values alone: the same values read as sRGB and as linear differ.
    by_content: dict[tuple[str, bool], Exemplar] = {}
    return tuple(by_content.setdefault((e.digest(), e.srgb), e) for e in read)


def _distinct(axes: Axes) -> list[Exemplar]:
    """The different exemplars among the three axes', in axis order."""
    return list({id(e): e for e in axes}.values())


def _pixels(axes: Axes) -> np.ndarray:
    """The pixels of the axes' different exemplars, as an (N, 1, C) image (one exemplar:
    itself), where the references that ignore neighbourhoods draw their colors from. Each
    pixel counts once, so a larger exemplar weighs more, as it would in a volume that
    matched every exemplar's histogram."""
    distinct = _distinct(axes)
    if len(distinct) == 1:
        return distinct[0].colors
    return np.concatenate([e.colors.reshape(-1, 1, e.colors.shape[2]) for e in distinct])


def large_edge(size: int, *exemplar_shapes: Sequence[int]) -> int:
    """Edge of the slice whose repetition score a comparison reports: at least
    :data:`LARGE`, and twice the longest period a method may repeat at (the volume, an
    exemplar), which :func:`warptex.metrics.repetition_score` sees up to half the slice."""
    return max(LARGE, 2 * size, *(2 * max(shape[:2]) for shape in exemplar_shapes))


def _edge(axes: Axes, size: int) -> int:
    return large_edge(size, *(e.shape for e in axes))


@dataclass(frozen=True)
class _Job:
    """What each method's functions are given in its process: the setup, its exemplars and,
    for the lazy engine's methods, the candidates pre-computed there (None: computed, or
    read from the cache, when first needed)."""

    setup: Setup
    axes: Axes
    candidates: object = None


def _candidates(job: _Job):
    """The job's candidates: those it holds, else the cache's (computed there if missing)."""
    from warptex.candidates import precompute

    if job.candidates is not None:
        return job.candidates
    return precompute(*job.axes, tileable=job.setup.tileable)


def _synthesizer(job: _Job):
    from warptex.synthesis import Synthesizer

    s = job.setup
    return Synthesizer(_candidates(job), seed=s.seed, jitter=s.jitter, passes=s.passes,
                       shifted_tiles=s.shifted_tiles)


def _lazy(job: _Job, size: int) -> np.ndarray:
    return _synthesizer(job).box((0, 0, 0), (size, size, size))


def _lazy_large(job: _Job, volume: np.ndarray) -> np.ndarray:
    edge = _edge(job.axes, volume.shape[0])
    return _synthesizer(job).box((0, 0, volume.shape[2] // 2), (edge, edge, 1))[:, :, 0]


def _kopf(job: _Job, size: int, mean_shift: bool = False) -> np.ndarray:
    from warptex.baselines.kopf import synthesize

    return synthesize(None, size=size, seed=job.setup.seed, progress=False,
                      exemplars=job.axes, mean_shift=mean_shift, tileable=job.setup.tileable)


def _tiled(job: _Job, size: int) -> np.ndarray:
    # The block of the usual practice is the lazy engine's own 64^3 here, so the difference
    # to `lazy` is the repetition, and above TILE voxels the seams where copies meet (the
    # engine's texture is not periodic; Fig. 11's block is).
    period = min(size, TILE)
    block = _lazy(job, period)
    reps = -(-size // period)
    return np.tile(block, (reps, reps, reps, 1))[:size, :size, :size]


def _tiled_large(job: _Job, volume: np.ndarray) -> np.ndarray:
    """The repeated block's z-slice repeated over the large slice: the tiled volume's own
    period, not that of a volume cut to a size the block does not divide."""
    period = min(volume.shape[0], TILE)
    return _tile_slice(volume[:period, :period, volume.shape[2] // 2],
                       _edge(job.axes, volume.shape[0]))


def _extrude(job: _Job, size: int) -> np.ndarray:
    return metrics.extrusion(_tile_slice(job.axes[2].colors, size), size, axis=2)


def _noise(job: _Job, size: int) -> np.ndarray:
    return metrics.iid_noise(_pixels(job.axes), (size, size, size), job.setup.seed)


def _flat(job: _Job, size: int) -> np.ndarray:
    pixels = _pixels(job.axes)
    mean = pixels.reshape(-1, pixels.shape[2]).mean(axis=0)
    return np.tile(mean.astype(pixels.dtype), (size, size, size, 1))


def _periodic_large(job: _Job, volume: np.ndarray) -> np.ndarray:
    """A periodic volume's z-slice repeated over the large slice."""
    return _tile_slice(volume[:, :, volume.shape[2] // 2], _edge(job.axes, volume.shape[0]))


def _noise_large(job: _Job, volume: np.ndarray) -> np.ndarray:
    edge = _edge(job.axes, volume.shape[0])
    return metrics.iid_noise(_pixels(job.axes), (edge, edge, 1), job.setup.seed + 1)[:, :, 0]


def _extrude_large(job: _Job, volume: np.ndarray) -> np.ndarray:
    return _tile_slice(job.axes[2].colors, _edge(job.axes, volume.shape[0]))


# Per method: the timed volume, and the large slice (at least 256 voxels, _edge) its
# repetition score looks at.
_RUN: dict[str, tuple[Callable[..., np.ndarray], Callable[..., np.ndarray]]] = {
    "lazy": (_lazy, _lazy_large),
    "kopf": (_kopf, _periodic_large),
    "kopf-meanshift": (functools.partial(_kopf, mean_shift=True), _periodic_large),
    "tiled": (_tiled, _tiled_large),
    "extrude": (_extrude, _extrude_large),
    "noise": (_noise, _noise_large),
    "flat": (_flat, _periodic_large),
}


def _tile_slice(image: np.ndarray, edge: int) -> np.ndarray:
    reps = (-(-edge // image.shape[0]), -(-edge // image.shape[1]), 1)
    return np.tile(image, reps)[:edge, :edge]


def _mitsuba():
    """Mitsuba in the best variant this machine supports, with the plugin registered."""
    import mitsuba as mi

    import mitsuba_plugin

    mitsuba_plugin.set_best_variant()
    mitsuba_plugin.register()
    return mi


_SKY = (0.5, 0.5, 0.55)  # radiance
_SUN_DIRECTION, _SUN_IRRADIANCE = (-0.4, -1.0, -0.7), (2.2, 2.1, 2.0)


def render_cube(texture: dict, resolution: int = 128) -> np.ndarray:
    """A unit cube at [0, 1]^3 wearing ``texture`` (a Mitsuba texture dict), seen from a
    corner under sky and sun; the (H, W, 3) image sRGB-encoded, as the sheet shows it.

    The sun is traced; the constant sky's light is added as albedo x sky radiance, its
    exact value on a convex object (every point sees the whole sky above it), and the sky
    behind the cube by the film's alpha. Path-traced, the sky left 16-spp noise of about
    12 % that made even a flat volume's cube look grainy; this is what that render
    converges to, with noise only in the pixels the cube's edges cut.
    """
    import mitsuba_plugin

    if not isinstance(texture, dict) or not isinstance(texture.get("type"), str):
        raise TypeError(f"texture must be a Mitsuba texture dict with a 'type', got {texture!r}")
    resolution = check_count("resolution", resolution, low=1)
    mi = _mitsuba()
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "aov", "aovs": "albedo:albedo",
                       "integrator": {"type": "path", "max_depth": 2}},
        "sensor": {
            "type": "perspective", "fov": 35,
            "to_world": T().look_at(origin=[2.6, 2.1, 2.9], target=[0.5, 0.45, 0.5], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": resolution, "height": resolution,
                     "rfilter": {"type": "box"}, "pixel_format": "rgba"},
            "sampler": {"type": "independent", "sample_count": _CUBE_SPP},
        },
        "sun": {"type": "directional", "direction": list(_SUN_DIRECTION),
                "irradiance": {"type": "rgb", "value": list(_SUN_IRRADIANCE)}},
        "cube": {"type": "cube", "to_world": T().translate([0.5, 0.5, 0.5]).scale(0.5),
                 "bsdf": {"type": "diffuse", "reflectance": texture}},
    })
    image = np.asarray(mitsuba_plugin.render(scene, batches=1))
    sunlit, alpha, albedo = image[..., :3], image[..., 3:4], image[..., 4:7]
    return linear_to_srgb(sunlit + (albedo + 1 - alpha) * np.asarray(_SKY))


def _cube_texture(method: str, job: _Job, volume: np.ndarray) -> dict:
    """``lazy`` renders through the ``lazy_solid`` plugin, which reads the exemplar files
    again (:func:`_check_unchanged` then makes sure they are those measured); the others
    through Mitsuba's own grid texture of their volume (both trilinear, one voxel = 1/size
    of the cube), decoded from sRGB as the plugin decodes the lazy one's."""
    s, axes = job.setup, job.axes
    size = volume.shape[0]
    if method == "lazy":
        loading = {} if s.max_size is None else {"exemplar_max_size": s.max_size}
        if s.feature_mask is not None:
            loading["feature_mask"] = str(s.feature_mask)
        elif s.feature_distance:
            loading["feature_distance"] = True
        paths = s.paths()
        exemplars = ({"exemplar": str(paths[0])} if len(_distinct(axes)) == 1 else
                     {f"exemplar_{a}": str(p) for a, p in zip("xyz", paths, strict=True)})
        return {"type": "lazy_solid", **exemplars, "seed": s.seed, "jitter": s.jitter,
                "shifted_tiles": s.shifted_tiles, "passes": s.passes,
                "tileable": tileable_word(s.tileable), "scale": float(size)} | loading
    # Gray where there are fewer than three channels, as the plugin shows them: Mitsuba's
    # grid volume takes 1, 3 or 6 channels.
    shown = volume[..., :3] if volume.shape[3] >= 3 else volume[..., :1]
    colors = reencoded(shown, srgb=axes[0].srgb, to_srgb=False)
    data = _mitsuba().TensorXf(np.ascontiguousarray(colors.transpose(2, 1, 0, 3)))
    return {"type": "volume", "volume": {"type": "gridvolume", "data": data,
                                         "filter_type": "trilinear"}}


def _check_unchanged(setup: Setup) -> None:
    """An ExemplarError naming the file unless each exemplar file still holds the image
    ``setup`` read: the lazy cube's plugin reads the files again, and would otherwise show
    an image the scores never saw."""
    for path, e in dict(zip(setup.paths(), setup.exemplars(), strict=True)).items():
        with captured():  # said when first read
            now = Exemplar.load(path, **setup.load_options())
        if now.digest() != e.digest():  # of the features too: a changed mask shows here
            raise ExemplarError(f"{path}: changed while the comparison ran; run it again")


def _precomputed(job: _Job) -> tuple[_Job, float]:
    """The job with the candidates of its exemplars computed afresh, and the seconds that
    took, its kernels compiled first on a small exemplar of as many channels."""
    from warptex.candidate_set import resolved_params
    from warptex.candidates import cache_path, precompute

    channels = job.axes[0].colors.shape[2]
    warm = np.random.default_rng(0).random((16, 16, channels), dtype=np.float32)
    precompute(Exemplar(warm), cache=False)
    start = time.perf_counter()
    candidates = precompute(*job.axes, tileable=job.setup.tileable, cache=False)
    seconds = time.perf_counter() - start
    # Cached as the lazy cube's plugin would cache them, which then reads them rather than
    # compute them again (minutes for a large exemplar); a cache that cannot be written
    # leaves the plugin to compute them as before.
    path = cache_path(list(job.axes), resolved_params({"tileable": job.setup.tileable}))
    if not path.exists():
        with contextlib.suppress(OSError):
            candidates.save(path)
    return replace(job, candidates=candidates), seconds


def _device_peak_mib(device: str) -> float | None:
    """High-water mark of Warp's memory pool on ``device`` in this process, in MiB; None on
    the CPU or where the device has no memory pool."""
    if not device.startswith("cuda"):
        return None
    import warp as wp

    try:
        return wp.get_mempool_used_mem_high(device) / 2**20
    except (ValueError, RuntimeError):
        return None


def _middle(size: int) -> int:
    """The index of the slices a sheet shows across each axis of a ``size``^3 volume."""
    return size // 2


def _measure(method: str, s: Setup, repeats: int = 1) -> dict:
    """Run one method in this (fresh) process: volume, scores, time (of ``repeats`` runs)
    and peak memory."""
    job = _Job(s, s.exemplars())
    axes, size = job.axes, s.size
    make_volume, make_large = _RUN[method]
    precompute_seconds = None
    if method == "lazy":
        _phase("pre-computing candidates")
        job, precompute_seconds = _precomputed(job)
    elif method in _LAZY:  # the same candidates, from the cache where a lazy run left them
        _phase("candidates, from the cache where they are")
        job = replace(job, candidates=_candidates(job))
    # Compile or load the Warp kernels outside the timing (cheap for the numpy methods).
    make_volume(job, 8)
    _phase(f"{size}^3, timed")
    runs = []
    with PeakMemory() as memory:
        for _ in range(repeats):
            volume = None  # not held while the next run makes its own: each run's peak
            start = time.perf_counter()
            volume = make_volume(job, size)
            runs.append(time.perf_counter() - start)
    device = _engine_device() if method in _LAZY else "cpu"
    device_peak = _device_peak_mib(device)
    _phase("its large slice, for the repetition score")
    large = make_large(job, volume)
    _phase("rendering its cube")
    render = render_cube(_cube_texture(method, job, volume))
    if method == "lazy":
        _check_unchanged(s)

    def per_axis(name: str, measure: Callable[[int], float]) -> list[float]:
        # Each axis' slices against its own Exemplar, whose seams are decided once.
        _phase(f"measuring {name}")
        return [measure(a) for a in range(3)]

    scores = {
        "energy": per_axis("energy", lambda a: metrics.neighborhood_energy(
            volume, axes[a], a, tileable=s.tileable)),
        "completeness": per_axis("completeness", lambda a: metrics.completeness_energy(
            volume, axes[a], a, tileable=s.tileable)),
        "swd": per_axis("sliced Wasserstein", lambda a: metrics.sliced_wasserstein(
            volume, axes[a], a, tileable=s.tileable)),
        "histogram": per_axis("histograms", lambda a: metrics.histogram_distance(
            volume, axes[a], a)),
    }
    _phase("measuring repetition")
    return {
        "method": method,
        **scores,
        "repetition": metrics.repetition_score(large),
        "seconds": float(np.median(runs)),
        "seconds_runs": runs,
        "peak_mib": memory.growth / 2**20,
        "slices": [metrics.axis_slice(volume, a, _middle(size)) for a in range(3)],
        "render": render,
        "notes": f"correction passes per level: {s.passes}" if method in _LAZY else "",
        "device": device,
        "precompute_seconds": precompute_seconds,
        "device_peak_mib": device_peak,
    }


def _engine_device() -> str:
    from warptex.warp_runtime import device

    return device()


def run_summary(size: int, seed: int) -> dict:
    """What a comparison's seconds and memory depend on: the volume, the machine that ran
    it (CPU model, cores, the threads a CPU launch is split over, GPU), the versions and the
    date."""
    import warp as wp

    from warptex.machine import cpu_model, software_versions, usable_cores
    from warptex.parallel import THREADS

    gpu = wp.get_device("cuda").name if _engine_device() == "cuda" else None
    versions = software_versions()
    return {"size": size, "seed": seed, "cpu": cpu_model(), "cores": usable_cores(),
            "threads": THREADS, "gpu": gpu, "warptex": versions.pop("warptex"),
            "warp": versions.pop("warp"), "versions": versions, "date": iso_date()}


def run_line(run: dict) -> str:
    """A :func:`run_summary` as one line of text: machine, versions and date."""
    gpu = f"GPU {run['gpu']}" if run["gpu"] else "no GPU"
    return (f"{run['cpu']}, {run['cores']} cores, {gpu}; warptex {run['warptex']}, "
            f"Warp {run['warp']}; {run['date']}")



def check_methods(methods: Iterable[str]) -> list[str]:
    """``methods`` as a list, refused (ValueError, TypeError) unless they are known
    methods, each given once: what :func:`compare` checks first, for callers that check
    before work of their own (the command, Kopf's sizes)."""
    if isinstance(methods, str):  # its letters would be taken for methods
        raise TypeError(f"methods must be a sequence of method names, such as "
                        f"[{methods!r}], got the string {methods!r}")
    try:
        methods = list(methods)  # an iterator is read more than once below
    except TypeError:
        raise TypeError(f"methods must be a sequence of method names, got {methods!r}") from None
    named = [m for m in methods if not isinstance(m, str)]
    if named:
        raise TypeError(f"methods must be method names (strings), got {named[0]!r}")
    unknown = [m for m in methods if m not in _RUN]
    if unknown:
        raise ValueError(
            f"unknown method(s) {', '.join(unknown)}; choose from {', '.join(METHODS)}"
        )
    if not methods:
        raise ValueError(f"no method given; choose from {', '.join(METHODS)}")
    repeated = sorted({m for m in methods if methods.count(m) > 1})
    if repeated:
        raise ValueError(f"method(s) given more than once: {', '.join(repeated)}")
    return methods


def compare(setup: Setup, methods: Sequence[str] = METHODS, *, progress: bool = True,
            repeats: int = 1) -> Comparison:
    """Score every method of ``methods`` on the exemplars of ``setup``, each in a fresh
    process (started by ``spawn``: a script calling this needs an ``if __name__ ==
    "__main__":`` guard), with the median of ``repeats`` timed runs as its seconds. A bad
    exemplar is refused before any method runs."""
    if not isinstance(setup, Setup):
        raise TypeError(f"setup must be a warptex.compare.Setup, got {setup!r}")
    methods = check_methods(methods)
    check_count("repeats", repeats, low=1)
    check_flag("progress", progress)
    axes = setup.exemplars()
    if any(m in _LAZY for m in methods):  # before any method's minutes of work
        from warptex.candidate_set import check_feature_channels
        from warptex.store import check_lookup_channels

        try:
            check_feature_channels(axes[0].features.shape[2])
            if "lazy" in methods:  # its cube is rendered through the plugin's lookups
                check_lookup_channels(axes[0].channels)
        except ValueError as error:
            raise ValueError(f"{setup.paths()[0]}: {error}") from None
    if any(m in _KOPF for m in methods):
        from warptex.baselines.kopf import check_channels, check_size

        check_size(setup.size)
        check_channels(axes)
    results = []
    ctx = multiprocessing.get_context("spawn")  # in_child_process's, for the phases' queue
    bar = tqdm(methods, desc="methods", disable=not progress)
    for method in bar:
        bar.set_postfix_str(method)  # one method can take minutes: the bar says which
        phases = ctx.Queue()  # and what it is doing: candidates alone can take a minute
        show = functools.partial(_show_phases, bar, method, phases)
        out = in_child_process(_measure, method, setup, repeats, initializer=_start_worker,
                               initargs=(_shown_as_here(), phases), while_waiting=show)
        show()
        results.append(MethodResult(**out))
    return Comparison(setup, results)


_phases: multiprocessing.queues.Queue | None = None  # where a method's process says it


def _phase(text: str) -> None:
    """Say, on the bar of the process that runs the comparison, what this method's process
    does now; nothing where it is not one (a test measuring in its own process)."""
    if _phases is not None:
        _phases.put(text)


def _show_phases(bar: tqdm, method: str, phases: multiprocessing.queues.Queue) -> None:
    """Show on ``bar`` each phase the method's process said since last looked."""
    with contextlib.suppress(queue.Empty, OSError, ValueError):
        while True:
            bar.set_postfix_str(f"{method}: {phases.get_nowait()}")


def _start_worker(show_warning: Callable | None,
                  phases: multiprocessing.queues.Queue | None = None) -> None:
    """A method's process: large blocks mapped afresh, for its peak memory; progress bars
    locked between threads only, for tqdm's default lock between processes is a semaphore
    that a worker stopped by :func:`~warptex.parallel.stop_workers` leaves to a warning at
    exit. Warnings are shown as the caller's process shows them (the command's one line),
    but for a dropped alpha, which :meth:`Setup.exemplars` reported already in compare's
    words."""
    map_large_blocks()
    std.tqdm.set_lock(threading.RLock())  # every kind of bar's
    if show_warning is not None:
        warnings.showwarning = show_warning
    warnings.simplefilter("ignore", AlphaDropped)
    global _phases
    _phases = phases


def _shown_as_here() -> Callable | None:
    """How this process shows warnings, where a worker can be given it (a function of a
    module, not one made in a notebook)."""
    try:
        pickle.dumps(warnings.showwarning)
    except (pickle.PicklingError, AttributeError, TypeError):
        return None
    return warnings.showwarning


def _trio(values: list[float]) -> str:
    """A per-axis metric as a table cell: "x / y / z"."""
    return " / ".join(f"{x:.3f}" for x in values)


def _cell(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def table_markdown(results: Sequence[MethodResult]) -> str:
    """The comparison table in Markdown: one row a method, per-axis metrics as x / y / z
    (the rows of ``table.md``); a column of device memory where a method ran on a GPU."""
    gpu = any(r.device_peak_mib is not None for r in results)
    lines = [
        "| method | energy x / y / z | completeness x / y / z | SWD x / y / z | "
        "histogram x / y / z | repetition | "
        "seconds | pre-computation s | peak MiB | " + ("GPU MiB | " if gpu else "")
        + "device | notes |",
        "|---|---|---|---|---|---|---|---|---|" + ("---|" if gpu else "") + "---|---|",
    ]
    for r in results:
        lines.append(f"| {r.method} | {_trio(r.energy)} | {_trio(r.completeness)} | "
                     f"{_trio(r.swd)} | {_trio(r.histogram)} | "
                     f"{r.repetition:.3f} | {r.seconds:.2f} | {_cell(r.precompute_seconds, 2)} | "
                     f"{r.peak_mib:.1f} | "
                     + (f"{_cell(r.device_peak_mib, 1)} | " if gpu else "")
                     + f"{r.device} | {r.notes} |")
    return "\n".join(lines) + "\n"


def _legend(measures: dict, repeats: int, gpu: bool = False) -> str:
    """What ``table.md``'s columns measure (:func:`_measure_settings`), below the table."""
    runs = "one wall-clock run" if repeats == 1 else f"the median of {repeats} wall-clock runs"
    return (
        f"\n{_scores_legend(measures)} "
        f"seconds: {runs} in a fresh process, kernels compiled first; "
        "pre-computation: the lazy engine's candidates, computed afresh (tiled reads them from "
        "the cache); peak MiB: rise of "
        "host memory during the run, pre-computation not included"
        + ("; GPU MiB: high-water mark of Warp's CUDA memory pool in the method's process, "
           "the pre-computation and the kernels' first run included" if gpu else "") + ".\n")


def _scores_legend(measures: dict) -> str:
    """What the scores measure, as ``table.md`` and ``table.json`` ("scores") say, for the
    ``measures`` (:func:`_measure_settings`) they were taken with."""
    edge, exclude = measures["repetition_slice"], measures["repetition_exclude"]
    return (
        "Lower is better in every score. energy: mean squared distance of slice patches to "
        "their nearest patch of that axis' exemplar, in units of its variance (it rewards blur: "
        "see `flat`); completeness: the same from each exemplar patch to its nearest slice "
        "patch (blur and flat volumes lack the sharp ones); SWD: sliced Wasserstein "
        "distance of the patches, which mostly sees "
        "colors (see `noise`); histogram: L1 distance of the color histograms, 0 to 2; "
        f"repetition: highest autocorrelation of a {edge}-voxel slice at a peak past "
        f"{exclude} voxels, 0 to 1 (warptex.metrics); the periodic volumes (tiled, Kopf's, "
        "flat) show their block tiled there. Scores of volumes of other sizes do not "
        "compare.")


def _title(paths: Sequence[Path], axes: Axes) -> str:
    """The exemplars as ``table.md``'s heading names them: the file, or each axis' file,
    with the size it was shrunk to where it was."""

    def named(path: Path, e: Exemplar) -> str:
        shrunk = "" if e.file_shape == e.shape else f", shrunk to {e.shape[1]}x{e.shape[0]}"
        return f"{path.name}{shrunk}"

    if len(_distinct(axes)) == 1:
        return named(paths[0], axes[0])
    return "; ".join(f"{a}: {named(p, e)}" for a, p, e in zip("xyz", paths, axes, strict=True))


def _defaults(function: Callable, *names: str) -> dict:
    """The default values of ``function``'s parameters ``names``: what a comparison that
    leaves them alone ran with."""
    import inspect

    parameters = inspect.signature(function).parameters
    return {name: parameters[name].default for name in names}


def _method_settings(methods: Sequence[str], s: Setup) -> dict:
    """The settings the lazy engine and Kopf ran with, for the methods among ``methods``."""
    from warptex.baselines import kopf
    from warptex.synthesis import Synthesizer

    out = {}
    if any(m in _LAZY for m in methods):
        out["lazy"] = {"passes": s.passes, "jitter": s.jitter,
                       "shifted_tiles": s.shifted_tiles} | _defaults(
            Synthesizer, "levels", "subpasses")
    if any(m in _KOPF for m in methods):
        out["kopf"] = _defaults(kopf.synthesize, "iterations", "histogram_matching")
    return out


def _measure_settings(edge: int) -> dict:
    """The parameters the measures ran with, ``edge`` the repetition slice's."""
    energy = _defaults(metrics.neighborhood_energy, "size", "slices")
    swd = _defaults(metrics.sliced_wasserstein, "directions", "seed")
    return {"patch": energy["size"], "patch_stride": metrics.PATCH_STRIDE,
            "completeness_patch_stride": metrics.COMPLETENESS_STRIDE,
            "slices": energy["slices"], "swd_directions": swd["directions"],
            "swd_seed": swd["seed"],
            "histogram_bins": _defaults(metrics.histogram_distance, "bins")["bins"],
            "repetition_exclude": _defaults(metrics.repetition_score, "exclude")["exclude"],
            "repetition_slice": edge}


def report_files(out_dir: str | Path) -> list[Path]:
    """The files :func:`write_report` writes into ``out_dir``, after a ValueError naming the
    first that cannot be written there (a file in the folder's place, say): refused so,
    not by an OSError from deep inside the writers."""
    files = [Path(out_dir) / name for name in REPORT_FILES]
    for path in files:
        problem = file_problem(path)
        if problem is not None:
            raise ValueError(f"{path}: {problem}")
    twice = one_file_twice(files)
    if twice is not None:
        raise ValueError(f"{twice[0]} and {twice[1]} are one file (a link to the other); "
                         "each report file is written once: remove the link")
    return files


def write_report(comparison: Comparison, out_dir: str | Path) -> list[Path]:
    """Write :data:`REPORT_FILES` (``sheet.png``, ``table.md``, ``table.json``) of a
    :func:`compare` into ``out_dir`` atomically, with the :func:`run_summary` of this
    machine and its :class:`Setup`: ``tileable`` as its word, and each axis' exemplar
    (``axis_exemplars``: file name, [width, height] as loaded, content digest), the x axis'
    also as ``exemplar`` (the file), ``exemplar_size`` and ``exemplar_digest``. The JSON's
    per-axis lists are in the order of its ``axes``."""
    from warptex.sheets import png_writer, sheet

    if not isinstance(comparison, Comparison) or not isinstance(comparison.setup, Setup):
        raise TypeError(f"comparison must be a warptex.compare.Comparison (what compare "
                        f"returns) of a Setup, got {comparison!r}")
    setup, results = comparison.setup, comparison.results
    sheet_file, markdown_file, json_file = files = report_files(out_dir)
    paths = setup.paths()
    axes = setup.exemplars()
    ex = axes[0]

    def shown(image: np.ndarray) -> np.ndarray:  # as an 8-bit picture shows colors: sRGB
        return reencoded(image, srgb=ex.srgb, to_srgb=True)

    one = len(_distinct(axes)) == 1
    rows = [("exemplar", [("exemplar", shown(ex.colors))] if one else
             [(f"{a} exemplar", shown(e.colors)) for a, e in zip("xyz", axes, strict=True)])]
    for r in results:
        images = [(f"{name} = {_middle(setup.size)}", shown(s))
                  for name, s in zip("xyz", r.slices, strict=True)]
        if r.render is not None:
            images.append(("rendered cube", r.render))
        rows.append((r.method, images))
    word = tileable_word(setup.tileable)
    measures = _measure_settings(_edge(axes, setup.size))
    repeats = max((len(r.seconds_runs) for r in results), default=1)
    run = run_summary(setup.size, setup.seed) | {
        "passes": setup.passes, "exemplar_max_size": setup.max_size,
        "feature_distance": setup.feature_distance or setup.feature_mask is not None,
        "feature_mask": None if setup.feature_mask is None else setup.feature_mask.name,
        "exemplar_size": list(ex.shape[::-1]),
        "exemplar_digest": ex.digest(),
        "axis_exemplars": [{"file": p.name, "size": list(e.shape[::-1]), "digest": e.digest()}
                           for p, e in zip(paths, axes, strict=True)],
        "tileable": word,
        "settings": _method_settings([r.method for r in results], setup),
        "measures": measures,
        "repeats": repeats, "scores": _scores_legend(measures), "timing": TIMING,
        "memory": MEMORY}
    told = "" if word == "auto" else f", tileable {word}"
    more = "".join((
        "" if setup.passes == DEFAULT_PASSES else f", {setup.passes} correction passes",
        "" if setup.jitter == DEFAULT_JITTER else f", jitter {setup.jitter:g}",
        ", shifted tiles" if setup.shifted_tiles else "",
        f", features from {setup.feature_mask.name}" if setup.feature_mask is not None else
        ", feature distance" if setup.feature_distance else ""))
    # Named on the sheet too, which is often passed around without its table.
    sheet_image = sheet(rows, title=f"{_title(paths, axes)}: {setup.size}^3, seed "
                                    f"{setup.seed}{more}{told}")
    markdown = (f"# {_title(paths, axes)}\n\n{setup.size}^3, seed {setup.seed}{more}{told}; "
                f"{run_line(run)}\n\n" + table_markdown(results)
                + _legend(measures, repeats, any(r.device_peak_mib is not None for r in results)))
    payload = [{k: v for k, v in asdict(r).items() if k not in ("slices", "render")}
               for r in results]
    table = json.dumps({"format": TABLE_FORMAT, "exemplar": paths[0].name,
                        "axes": list("xyz"), "run": run, "methods": payload}, indent=2)
    # Together, once all three are made: a failure leaves the last report whole.
    write_together([(sheet_file, png_writer(sheet_image)),
                    (markdown_file, lambda tmp: tmp.write_text(markdown)),
                    (json_file, lambda tmp: tmp.write_text(table))])
    return files

