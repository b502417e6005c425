"""The methods a comparison sets side by side (Dong 2008, 6.3 and Fig. 11; Kopf 2007): the
volume each makes, the large slice its repetition score looks at, and the rendered cube
that wears it, through the ``lazy_solid`` plugin for lazy synthesis."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from warptex import metrics
from warptex.compare.setup import Axes, Setup, _distinct
from warptex.settings import check_count, tileable_word
from warptex.srgb import linear_to_srgb, reencoded

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


def _middle(size: int) -> int:
    """The index of the slices a sheet shows across each axis of a ``size``^3 volume."""
    return size // 2


def _engine_device() -> str:
    from warptex.warp_runtime import device

    return device()


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
    again (:func:`.measure._check_unchanged` then makes sure they are those measured); the
    others through Mitsuba's own grid texture of their volume (both trilinear, one voxel =
    1/size of the cube), decoded from sRGB as the plugin decodes the lazy one's."""
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
