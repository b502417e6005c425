"""The ``lazy_solid`` Mitsuba texture: colors synthesized on demand at shading points.

Properties (XML or ``mi.load_dict``):

=====================  =========  ==============================================================
``exemplar``           string     exemplar image; relative paths are taken from the scene file's
                                  folder (``mi.load_dict``: the working directory)
``exemplar_x``         string     optional exemplars of the three axes (Dong 2008, section 4):
``_y``, ``_z``                    x's defaults to ``exemplar``, y's to x's, z's to y's
``exemplar_max_size``  integer    shrink larger exemplars (area-averaged) until their larger side
                                  is this many pixels, at least 16 (default: as they are)
``feature_distance``   boolean    add a feature-distance channel (Lefebvre & Hoppe 2006) from an
                                  automatic luminance threshold to each exemplar (default false)
``feature_mask``       string     binary image marking the features of ``exemplar`` (one
                                  exemplar only), from which that channel is taken instead
``seed``               integer    synthesis seed, 0 to 2147483647 (default 0)
``jitter``             float      coarse-level jitter of the synthesis, 0 to 64 (default 1.0)
``shifted_tiles``      boolean    shift each tile of the initial tiling by its own offset, so
                                  structured exemplars show no bands every exemplar width, at
                                  some cost in likeness (default false)
``tileable``           string     whether synthesis may continue the exemplar across its
                                  opposite edges: ``auto`` (default) where they differ no
                                  more than neighbouring pixels do, ``yes`` always (the paper's
                                  tori), ``no`` never
``passes``             integer    correction passes per pyramid level, 0 to 8 (default 2; 3 come
                                  closer to the exemplar at about twice the synthesis time, see
                                  ``docs/comparisons``)
``scale``              float      voxels per scene unit (default 64)
``to_world``           transform  places the block of matter (default identity)
``space``              string     ``world`` (default) or ``object``, see below
``filter``             string     ``trilinear`` (default) or ``nearest``
``raw``                boolean    render an 8- or 16-bit exemplar's values as they are stored,
                                  without decoding sRGB (default false, as Mitsuba's ``bitmap``)
``cache``              string     brick store file: loaded when it exists, written by ``save()``
                                  (not in scenes loaded within ``stores_read_only()``); refused
                                  when a live texture of other settings has it
``cache_bytes``        integer    memory bound of the brick store (default 256 MiB; scalar
                                  variants keep up to about as much again, see below)
=====================  =========  ==============================================================

A scene point p has texture coordinates ``scale * to_world^-1 * p``: one texture unit is
one finest voxel (see :mod:`warptex.texture`). The texture never stops a render: beyond its
coordinate range (``POINT_LIMIT``) points are moved by whole periods of 2^22 voxels
(:func:`warptex.texture.wrap_far`), the same in every mode, and NaN or infinite ones are black.
With ``space="object"`` p is first taken into the frame of the object that was hit, so the
texture sticks to it when it moves: the frame of the ``instance`` the hit belongs to, else
the ``to_world`` parameter of the shape when it has one (``sphere``, ``rectangle``, ...).
Meshes bake their ``to_world`` into their vertices at load time, so a plain mesh has no frame
to recover and object space equals world space for it; move meshes with ``instance`` to keep
their texture. So do shapes that Mitsuba's loader merges into one mesh (``optimize=True``, its
default, merges rectangles and meshes that share a BSDF): give each moving shape its own BSDF,
or an ``instance``.

Colors: as Mitsuba's ``bitmap`` does, the plugin gives renders linear colors, so the
sRGB-encoded values of 8- and 16-bit exemplars (``Exemplar.srgb``) are decoded unless
``raw`` is set; float exemplars (OpenEXR, ``.npy``) are linear already. Synthesis and the
brick store keep the stored values; the plugin decodes the filtered color of each point.
Mitsuba's bitmap decodes texels before filtering instead: the same at voxel centres and with
the ``nearest`` filter, darker half way between voxels, by 0.003 where two mid-gray
neighbours differ by 0.1 and 0.026 where they differ by 0.3. Unlike the bitmap's ``raw``, this
one leaves spectral upsampling on. The decoding widens colors to float64 and rounds the
result to float32, as :func:`warptex.srgb.srgb_to_linear` does: the scalar and the LLVM
variants and NumPy give a point the same bits (float32 powers differ between them in the
last bits); the CUDA variants should too (not yet checked on a GPU).

Variants: ``eval`` gives the color as the variant's spectrum (:mod:`mitsuba_plugin.spectrum`:
as it is in RGB variants, its luminance in monochrome ones, Mitsuba's upsampling of it in
spectral ones); ``eval_3`` is always the RGB color, ``eval_1`` its luminance. ``bumpmap``
reads ``eval_1_grad`` (forward differences half a voxel of ``scale`` and ``to_world`` long
along ``dp_du`` and ``dp_dv``), and
light tracing from a textured emitter ``sample_spectrum`` (wavelengths sampled as for
Mitsuba's color-based spectra).

Rendering modes (JIT variants): synthesis runs in Warp kernels, outside Dr.Jit's traced
programs. Render with :func:`mitsuba_plugin.render`: it traces the lookup of stored
voxels into Mitsuba's program (:mod:`mitsuba_plugin.traced`), synthesizes what a render
missed and renders again, and falls back to wavefront mode (Dr.Jit's ``SymbolicLoops``
and ``SymbolicCalls`` off, so ``eval`` gets the concrete points of a whole wavefront)
when a texture cannot be traced: its stored bricks scattered too widely for one page
table, a render that keeps reaching new bricks, or a CUDA variant (there Dr.Jit's float32
division is approximate and the GPU compiler may fuse its multiply-adds, so traced colors
could differ from the Warp lookups' in the last bits). Your own symbolic renders
(differentiable ones, say) trace the same lookups inside a
:func:`mitsuba_plugin.traced_renders` block. Outside these ``eval`` raises inside a
symbolic scope, so a plain ``mi.render`` never shows voxels that were not synthesized.

Scalar variants evaluate one point at a time, from host copies of the bricks read
(:mod:`mitsuba_plugin.scalar`, up to about ``cache_bytes`` more); a point they lack is left to
the store, which synthesizes it. Any render works there, ``mi.render`` included.
"""

from __future__ import annotations

import difflib
import math
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

import mitsuba_plugin
from mitsuba_plugin.properties import (
    check_known,
    choice_property,
    existing_scene_file,
    get_property,
    property_error,
    scene_path,
)
from mitsuba_plugin.scalar import ScalarLookup
from mitsuba_plugin.spectrum import check_upsampling, luminance, spectrum
from mitsuba_plugin.traced import TracedLookup
from warptex.affine import affine_inverse, apply_affine
from warptex.archive import file_problem
from warptex.candidate_set import CandidateSet
from warptex.candidates import precompute
from warptex.exemplar import AlphaDropped, Exemplar, srgb_encoded
from warptex.float_env import ieee_arithmetic
from warptex.settings import (
    DEFAULT_CACHE_BYTES,
    DEFAULT_JITTER,
    DEFAULT_PASSES,
    FILTERS,
    TILEABLE,
    SettingError,
    check_max_size,
    check_settings,
    names_folder,
)
from warptex.srgb import srgb_decoded, srgb_to_linear
from warptex.store import check_lookup_channels
from warptex.store_files import StoreFileError, check_store_path
from warptex.texture import SolidTexture, wrap_far
from warptex.thread_warnings import Warned, captured

PLUGIN = "lazy_solid"
_SPACES = ("world", "object")
# Pixel triples whose voxel colors estimate the mean of a texture decoded from sRGB.
_MEAN_SAMPLES = 1 << 16
_DEFAULT_SCALE = 64.0
_PROPERTIES = ("exemplar", "exemplar_x", "exemplar_y", "exemplar_z", "exemplar_max_size",
               "feature_distance", "feature_mask", "seed", "jitter", "shifted_tiles",
               "tileable", "passes", "scale", "space", "filter", "raw", "cache_bytes", "cache",
               "to_world")


def _exemplar_paths(props: mi.Properties) -> list[tuple[str, Path]]:
    """The exemplars of the x, y and z axes, each checked to exist, with the property that
    names each: ``exemplar_x`` defaults to ``exemplar``, ``exemplar_y`` to x's and
    ``exemplar_z`` to y's, as ``precompute`` and the commands' --ey/--ez take them
    (``warptex.exemplar.axis_triple``), so a scene and a command given the same images
    synthesize the same solid."""
    plain = get_property(props, "exemplar", str, None, PLUGIN)
    if plain is not None and "exemplar_x" in props:
        raise property_error(PLUGIN, "exemplar", 'and "exemplar_x" name the same axis: give '
                             "one of them")
    named: list[tuple[str, Path]] = []
    for axis in "xyz":
        key = f"exemplar_{axis}"
        if key in props:
            named.append((key, existing_scene_file(get_property(props, key, str, None, PLUGIN),
                                                   key, PLUGIN)))
        elif named:
            named.append(named[-1])
        elif plain is not None:
            named.append(("exemplar", existing_scene_file(plain, "exemplar", PLUGIN)))
        else:
            unread = [k for k in props if k not in _PROPERTIES]
            # Mitsuba's bitmap names its image "filename": a scene moved over from it.
            near = (["filename"] if "filename" in unread
                    else difflib.get_close_matches("exemplar", unread, n=1))
            typo = f' ("{near[0]}" is no property of {PLUGIN})' if near else ""
            raise property_error(PLUGIN, "exemplar", f'is required (or "exemplar_x"){typo}')
    return named


def _feature_options(props: mi.Properties, named: list[tuple[str, Path]]) -> dict:
    """``Exemplar.load``'s feature options (Lefebvre & Hoppe 2006's feature-distance
    channel, which the candidates match beside the colors), as the properties give them."""
    automatic = get_property(props, "feature_distance", bool, False, PLUGIN)
    mask = get_property(props, "feature_mask", str, None, PLUGIN)
    if mask is None:
        return {"feature_distance": automatic}
    if automatic:
        raise property_error(PLUGIN, "feature_mask", 'and "feature_distance" exclude each '
                             "other: the mask marks the features the distance is taken from")
    if any(key != "exemplar" for key, _ in named):
        raise property_error(PLUGIN, "feature_mask", 'marks the pixels of one "exemplar"; '
                             'with "exemplar_x", ... use "feature_distance"')
    return {"feature_mask": existing_scene_file(mask, "feature_mask", PLUGIN)}


def _load_exemplars(named: list[tuple[str, Path]], max_size: int | None,
                    **features: Any) -> list[Exemplar]:
    """The exemplar images, each read once, shrunk to ``max_size`` and given the
    ``features`` of :func:`_feature_options`; one that cannot be read is blamed on the
    property that names it (the mask's errors name the mask's file)."""
    loaded: dict[Path, Exemplar] = {}
    mask = features.get("feature_mask")
    for key, path in named:
        if path in loaded:
            continue
        try:
            # Of this thread only: Mitsuba builds a scene's textures on several threads.
            with captured() as said:
                loaded[path] = Exemplar.load(path, max_size=max_size, **features)
        except (ValueError, OSError, Warning) as e:  # a warning of Pillow's made an error
            # Exemplar.load's errors begin with the file at fault.
            at_fault = ("feature_mask" if mask is not None and str(e).startswith(f"{mask}: ")
                        else key)
            raise property_error(PLUGIN, at_fault, f"cannot be used: {e}") from e
        for warning in said:
            _rewarn(warning, path)
    return [loaded[path] for _, path in named]


def _rewarn(warning: Warned, path: Path) -> None:
    """A warning of Exemplar.load as a scene's author reads it: the plugin has no alpha
    property to keep the channel with, as the API and the command line have."""
    message = warning.message
    if issubclass(warning.category, AlphaDropped):
        message = f"{path}: alpha channel dropped ({PLUGIN} gives colors only)"
    # Past _load_exemplars, LazySolidTexture._candidates and __init__: the scene's loader.
    warnings.warn(f"{PLUGIN}: {message}", warning.category, stacklevel=5)


def _exemplar_names(named: list[tuple[str, Path]]) -> str:
    """The exemplar properties of :func:`_exemplar_paths`, as an error names them: the
    per-axis ones where any is given, since those are what differ from the others."""
    axes = dict.fromkeys(key for key, _ in named if key != "exemplar")
    return '", "'.join(axes) if axes else "exemplar"


def _affine_matrix(transform: Any) -> np.ndarray:
    """The 4x4 float64 matrix of a Mitsuba transform (scalar or width-1 JIT)."""
    matrix = np.array(transform.matrix, np.float64)
    return matrix.reshape(4, 4)


def _recorded_matrix(transform: Any) -> list[list[float]]:
    """The 4x4 matrix of a Mitsuba transform as a report records it: each entry the shortest
    decimal that reads back as the value held (float32 in most variants), so that the
    recorded texture places the block exactly where the render did, however small its scale."""
    matrix = np.array(transform.matrix).reshape(4, 4)
    return [[float(np.format_float_positional(v, unique=True)) for v in row] for row in matrix]


def _to_world(props: mi.Properties) -> np.ndarray:
    """The ``to_world`` property's matrix in float32, as the texture keeps it: a transform
    that can be inverted, since shading points are taken into the block of matter it
    places."""
    value = props.get("to_world", mi.ScalarTransform4f())
    try:
        matrix = _affine_matrix(value)
    except (AttributeError, TypeError, ValueError):
        raise property_error(PLUGIN, "to_world",
                             f"must be a <transform ...>, got {value!r}") from None
    with np.errstate(over="ignore"):  # said below, in words, not as NumPy's warning
        single = matrix.astype(np.float32)
    if np.isfinite(matrix).all() and not np.isfinite(single).all():
        raise property_error(PLUGIN, "to_world", "is beyond float32's range, in which the "
                             "texture keeps it (entries up to 3.4e38)")
    _inverse(single.astype(np.float64))
    return single


def _inverse(to_world: np.ndarray) -> np.ndarray:
    """The inverse of a ``to_world`` matrix, as loaded or as a parameter update sets it,
    after the property's error unless it is finite, affine and invertible."""
    if not np.isfinite(to_world).all():
        raise property_error(PLUGIN, "to_world", "must be finite: it has NaN or infinite "
                             "entries")
    # Shading points are mapped by the first three rows, which would drop a projective last.
    if not np.array_equal(to_world[3], [0.0, 0.0, 0.0, 1.0]):
        row = " ".join(f"{c:g}" for c in to_world[3])
        raise property_error(PLUGIN, "to_world", f"must be affine: its last row is {row}, "
                             "not 0 0 0 1")
    inverse = _finite_inverse(to_world)
    if inverse is None:
        raise property_error(PLUGIN, "to_world", "must be invertible: a scale of zero "
                             "collapses the block of matter")
    return inverse


def _finite_inverse(matrix: np.ndarray) -> np.ndarray | None:
    """The inverse of affine ``matrix``, None where it has none in finite numbers; alike on
    every machine (LAPACK's differed in its last bits between CPUs, and so did the voxels of
    points on their borders)."""
    return affine_inverse(matrix) if np.isfinite(matrix).all() else None


class LazySolidTexture(mi.Texture):
    """A solid texture synthesized lazily by warptex (Dong et al. 2008).

    Reads its properties once (see the module documentation), then every ``eval``
    turns the shading points into texture coordinates and asks the brick store for their
    colors; bricks are synthesized on first touch and kept.
    """

    def __init__(self, props: mi.Properties) -> None:
        super().__init__(props)
        check_upsampling()  # before any work: this Mitsuba's spectra may be refused
        named = _exemplar_paths(props)
        check_known(props, _PROPERTIES, PLUGIN)
        self.exemplars = [path for _, path in named]
        features = _feature_options(props, named)
        self.feature_distance = bool(features.get("feature_distance", False))
        self.feature_mask = features.get("feature_mask")
        self._read_settings(props)
        self._read_only = mitsuba_plugin.stores_are_read_only()
        store = self._store_to_load()
        # A JIT-typed transform, so mi.traverse can update it in place.
        self.to_world = mi.AffineTransform4f(_to_world(props))
        # Mitsuba builds nested textures on its threads, which flush denormals to zero:
        # the exemplars read and candidates computed as on any other (warptex.float_env).
        with ieee_arithmetic():
            candidates = self._candidates(named, features)
            self.solid = self._solid_texture(candidates, store)
            self._set_color_range(_axis_colors(candidates))
        self._traced: TracedLookup | None = None
        # The scalar variants' copies of bricks, as large as the store may be.
        self._scalar = (None if dr.is_jit_v(mi.Float)
                        else ScalarLookup(self.solid.store, self.filter, self.cache_bytes))
        self._frames: _ObjectFrames | None = None
        # The one shape whose area light this texture colours, for the points that light
        # tracing emits from it, which carry no shape: during renders only (emitting_in),
        # of which ``_emitting`` are under way.
        self._emitter: mi.Shape | None = None
        self._emitting = 0
        self._emitting_lock = threading.Lock()
        self._tracing: int | None = None  # the thread whose render traces this texture
        self._inert = False  # traced as another scene's texture that cannot be traced
        self._update_transform()
        mitsuba_plugin.live_textures.add(self)

    def _read_settings(self, props: mi.Properties) -> None:
        """The synthesis, mapping and store properties, each checked as it is read."""
        self.max_size = get_property(props, "exemplar_max_size", int, None, PLUGIN)
        try:
            check_max_size(self.max_size)
        except SettingError as e:
            raise property_error(PLUGIN, "exemplar_max_size", e.problem) from None
        self.seed = get_property(props, "seed", int, 0, PLUGIN)
        self.jitter = get_property(props, "jitter", float, DEFAULT_JITTER, PLUGIN)
        self.shifted_tiles = get_property(props, "shifted_tiles", bool, False, PLUGIN)
        self.tileable = choice_property(props, "tileable", tuple(TILEABLE), PLUGIN)
        self.passes = get_property(props, "passes", int, DEFAULT_PASSES, PLUGIN)
        try:
            check_settings(self.jitter, self.passes, self.seed)
        except SettingError as e:
            raise property_error(PLUGIN, e.name, e.problem) from None
        self.scale = get_property(props, "scale", float, _DEFAULT_SCALE, PLUGIN)
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise property_error(PLUGIN, "scale", f"must be a positive number, got {self.scale}")
        self.space = choice_property(props, "space", _SPACES, PLUGIN)
        self.filter = choice_property(props, "filter", FILTERS, PLUGIN)
        self.raw = get_property(props, "raw", bool, False, PLUGIN)
        self.cache_bytes = get_property(props, "cache_bytes", int, DEFAULT_CACHE_BYTES, PLUGIN)
        if self.cache_bytes < 0:
            raise property_error(PLUGIN, "cache_bytes",
                                 f"must not be negative, got {self.cache_bytes}")
        cache = get_property(props, "cache", str, None, PLUGIN)
        if cache is not None and names_folder(cache):
            raise property_error(PLUGIN, "cache", f'names a folder, not a file: "{cache}"')
        self.cache = None if cache is None else scene_path(cache, must_exist=False)

    def _store_to_load(self) -> Path | None:
        """The store file to load the bricks of, if any: the ``cache`` file, where it exists
        or may be saved to."""
        # A store file yet to be made that never can be would only fail its first save,
        # after a render's work; one that exists is loaded even from a read-only place.
        if self.cache is None or self.cache.exists():
            return self.cache
        if self._read_only:
            return None  # nothing to read, and nothing will be saved
        problem = file_problem(self.cache)
        if problem is not None:
            raise property_error(PLUGIN, "cache", f"cannot be saved to {self.cache}: {problem}")
        return self.cache

    def _candidates(self, named: list[tuple[str, Path]], features: dict) -> CandidateSet:
        """The exemplars' candidates (pre-computed, or from the cache), after a property
        error naming the exemplars where they cannot be used together."""
        exemplars = _load_exemplars(named, self.max_size, **features)
        try:
            self._decode_srgb = not self.raw and srgb_encoded(exemplars)
            check_lookup_channels(exemplars[0].channels)  # before pre-computing
            return precompute(*exemplars, progress=mitsuba_plugin.candidates_bar(),
                              tileable=TILEABLE[self.tileable])
        except ValueError as e:  # ExemplarError included; exemplars that do not go together
            raise property_error(PLUGIN, _exemplar_names(named), f"cannot be used: {e}") from e

    def _solid_texture(self, candidates: CandidateSet, store: Path | None) -> SolidTexture:
        """The solid texture of these settings, its bricks loaded from ``store``; a store
        file it ignores is warned of under the ``cache`` property."""
        try:
            if self._read_only and store is not None:  # read, never saved: said as such
                check_store_path(store, saving=False)
            with captured() as said:  # a store file ignored
                solid = SolidTexture(candidates, seed=self.seed, jitter=self.jitter,
                                     passes=self.passes, cache_bytes=self.cache_bytes,
                                     store=store, shifted_tiles=self.shifted_tiles)
        except StoreFileError as e:
            raise property_error(PLUGIN, "cache", f"cannot be used: {e}") from e
        for warning in said:
            warnings.warn(f'{PLUGIN}: property "cache": {warning.message}', warning.category,
                          stacklevel=3)
        if solid.store.cache_bytes < solid.store.brick_bytes:  # renders read voxels back
            warnings.warn(f'{PLUGIN}: property "cache_bytes": {solid.store.cache_bytes} bytes '
                          f"keep no brick of voxels (one takes {solid.store.brick_bytes}): "
                          "every render synthesizes them again", stacklevel=3)
        return solid

    def _set_color_range(self, axes: list[np.ndarray]) -> None:
        """What stands in for voxels not yet stored, and what ``eval`` gives on average and
        at least and at most, from the exemplars' colors ``axes``."""
        # Traced lookups give voxels not yet stored this color, in stored values as theirs.
        self._stand_in = tuple(float(c) for c in np.mean([a.mean(axis=0) for a in axes], 0))
        # What eval gives on average (the mean channel; luminance in a monochrome variant)
        # and at most (spectra may exceed a color's largest channel, but never 1).
        mean_rgb, min_rgb, max_rgb = _voxel_color_range(axes, self._decode_srgb)
        self._mean = float(mean_rgb.mean())
        # No channel of it is lower (a medium refuses an extinction that may be negative)
        # or higher (the bound of an extinction upsampled unbounded).
        self.lowest, self.largest = float(min_rgb.min()), float(max_rgb.max())
        if mi.is_monochromatic:
            self._mean = float(np.ravel(luminance(mi.Color3f(*map(float, mean_rgb))))[0])
        self._max = 1.0 if mi.is_spectral else self.largest

    # -- mi.Texture interface ---------------------------------------------------------

    def eval(self, si: mi.SurfaceInteraction3f, active: mi.Bool = True) -> mi.UnpolarizedSpectrum:
        return spectrum(self.colors_at(si, active), si.wavelengths)

    def eval_3(self, si: mi.SurfaceInteraction3f, active: mi.Bool = True) -> mi.Color3f:
        return self.colors_at(si, active)

    def eval_1(self, si: mi.SurfaceInteraction3f, active: mi.Bool = True) -> mi.Float:
        return luminance(self.colors_at(si, active))

    def sample_spectrum(self, si: mi.SurfaceInteraction3f, sample: Any,
                        active: mi.Bool = True) -> tuple[Any, mi.UnpolarizedSpectrum]:
        """Wavelengths for an emitter's radiance (light tracing, ``sample_ray``): sampled
        over the visible range as Mitsuba's color-based spectra do, each weighted by the
        texture's spectrum there; in RGB and monochrome variants the color as it is."""
        if not mi.is_spectral:
            return si.wavelengths, self.eval(si, active)
        wavelengths, weight = mi.sample_rgb_spectrum(sample)
        at = mi.SurfaceInteraction3f(si)
        at.wavelengths = wavelengths
        return wavelengths, weight * self.eval(at, active)

    def eval_1_grad(self, si: mi.SurfaceInteraction3f, active: mi.Bool = True) -> mi.Vector2f:
        """Gradient of ``eval_1`` with respect to the surface's (u, v), as ``bumpmap`` reads
        it: forward differences half a voxel long along ``dp_du`` and ``dp_dv`` (a solid
        texture has no UV parametrization of its own), voxels as ``scale`` and ``to_world``
        size them, and in object space the shape's or instance's own frame too. In float64,
        each result rounded to float32 once, in one order of operations: Mitsuba's scalar and
        LLVM builds compute ``dr.norm`` an ulp apart, and the variants' gradients must agree
        as their colors do."""
        wide = dr.float64_array_t(mi.Float)
        base = wide(self.eval_1(si, active))
        p = [wide(c) for c in si.p]
        here = self._in_object_frames(si, p, active) if self.space == "object" else None
        slopes = []
        for dp in (si.dp_du, si.dp_dv):
            d = [wide(c) for c in dp]
            # Voxels along dp, per unit of u: a to_world that scales the texture, or the
            # object's frame in object space, scales them.
            e = d
            if here is not None:
                ahead = self._in_object_frames(si, [c + k for c, k in zip(p, d, strict=True)],
                                               active)
                e = [b - a for a, b in zip(here, ahead, strict=True)]
            t = [row[0] * e[0] + row[1] * e[1] + row[2] * e[2]
                 for row in self._world_to_texture[:3]]
            voxels = dr.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2])
            # A degenerate parametrization (dp = 0) stays in place and has no slope.
            step = 0.5 / dr.maximum(voxels, 1e-30)
            moved = mi.SurfaceInteraction3f(si)
            moved.p = mi.Point3f(*(mi.Float(c + step * e) for c, e in zip(p, d, strict=True)))
            rise = wide(self.eval_1(moved, active)) - base
            slopes.append(mi.Float(rise * (2.0 * voxels)))
        return mi.Vector2f(*slopes)

    def _in_object_frames(self, it: mi.Interaction3f, p: list, active: mi.Bool) -> list:
        """World points ``p`` (float64, a lane each) of ``it`` in the frame of the object
        each lane was found on, as the lookups of the mode at hand take them."""
        if dr.flag(dr.JitFlag.SymbolicScope):
            return self._frames.to_object(it, p)
        if not dr.is_jit_v(mi.Float):  # the scalar variants: one point
            point = np.array([[float(c) for c in p]])
            return [float(c) for c in _to_object_space(point, it, None, self._emitter)[0]]
        width = dr.width(it.p)
        keep = (mi.Bool(active) | dr.zeros(mi.Bool, width)).numpy()
        points = np.stack([np.broadcast_to(c.numpy(), width) for c in p], axis=1)
        out = points.copy()
        if keep.any():
            out[keep] = _to_object_space(points[keep], it, keep, self._emitter)
        return [mi.Float64(out[:, k]) for k in range(3)]

    def mean(self) -> mi.Float:
        return mi.Float(self._mean)

    def max(self) -> float:
        return self._max

    def is_spatially_varying(self) -> bool:
        return True

    def traverse(self, callback: mi.TraversalCallback) -> None:
        callback.put("to_world", self.to_world, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys: list[str] | None = None) -> None:
        try:
            self._update_transform()
        except ValueError:
            # Refused: back to the matrix eval still uses, for properties() to report; in
            # place, as mi.traverse holds this object.
            self.to_world.assign(mi.AffineTransform4f(self._placed))
            raise

    def properties(self) -> dict:
        """Every property that sets what a point shows, as read from the scene (the
        exemplars per axis, x, y, z; ``to_world`` as a 4x4 matrix): what `warptex render`
        records of each texture."""
        return {"exemplars": [str(p) for p in self.exemplars],
                "exemplar_max_size": self.max_size, "feature_distance": self.feature_distance,
                "feature_mask": None if self.feature_mask is None else str(self.feature_mask),
                "seed": self.seed, "jitter": self.jitter,
                "shifted_tiles": self.shifted_tiles, "tileable": self.tileable,
                "passes": self.passes, "scale": self.scale,
                "to_world": _recorded_matrix(self.to_world),
                "space": self.space, "filter": self.filter, "raw": self.raw,
                "cache": None if self.cache is None else str(self.cache),
                "cache_bytes": self.cache_bytes}

    def to_string(self) -> str:
        p = self.properties()
        if len(set(p["exemplars"])) == 1:
            names = f'"{p["exemplars"][0]}"'
        else:
            names = ", ".join(f'{axis}="{e}"' for axis, e in zip("xyz", p["exemplars"],
                                                                  strict=True))
        shrunk = ("" if p["exemplar_max_size"] is None
                  else f", exemplar_max_size={p['exemplar_max_size']}")
        if p["feature_mask"] is not None:
            shrunk += f', feature_mask="{p["feature_mask"]}"'
        elif p["feature_distance"]:
            shrunk += ", feature_distance=True"
        placed = "" if np.array_equal(p["to_world"], np.eye(4)) else f", to_world={p['to_world']}"
        return (f"LazySolidTexture[exemplars=[{names}]{shrunk}, seed={p['seed']}, "
                f"jitter={p['jitter']}, shifted_tiles={p['shifted_tiles']}, "
                f"tileable={p['tileable']}, passes={p['passes']}, scale={p['scale']}{placed}, "
                f"space={p['space']}, filter={p['filter']}, raw={p['raw']}, "
                f"cache={p['cache']}, cache_bytes={p['cache_bytes']}]")

    # -- queries ----------------------------------------------------------------------

    def colors_at(self, it: mi.Interaction3f, active: mi.Bool = True) -> mi.Color3f:
        """RGB at the points of interaction ``it`` where ``active``, zero elsewhere: the
        stored colors, decoded from sRGB to linear unless ``raw`` (module documentation)."""
        if not dr.is_jit_v(mi.Float):
            if not active:
                return mi.Color3f(0.0)
            rgb = self._scalar_color(it)
            return mi.Color3f(*(map(_srgb_decoded, rgb) if self._decode_srgb else rgb))
        rgb = self._jit_colors(it, active)
        if not self._decode_srgb:
            return rgb
        return mi.Color3f(srgb_decoded(dr.float64_array_t(mi.Color3f)(rgb), dr.select))

    def _query_texture_space(self, points: np.ndarray) -> np.ndarray:
        """RGB (N, 3) float32 at texture-space ``points`` (N, 3), as stored (not decoded):
        beyond the texture's coordinate range as :func:`warptex.texture.wrap_far` moves
        them, black where a point is NaN or infinite, as Mitsuba's textures never raise."""
        return _as_rgb(self.solid.query(wrap_far(points), filter=self.filter, fill=0.0))

    def _jit_colors(self, it: mi.Interaction3f, active: mi.Bool) -> mi.Color3f:
        """RGB at the points of ``it`` where ``active``, as stored; zero elsewhere (JIT
        variants).

        Only the active lanes are queried, so inactive lanes synthesize nothing; the LLVM
        variants hand their points to NumPy without a copy (DLPack).
        """
        if dr.flag(dr.JitFlag.SymbolicScope):
            if self._tracing != threading.get_ident():
                raise RuntimeError(f"{PLUGIN}: render with mitsuba_plugin.render, which "
                                   "synthesizes what a symbolic render reads, inside a "
                                   "mitsuba_plugin.traced_renders block (backward passes "
                                   "too), or in wavefront mode (Dr.Jit's SymbolicLoops and "
                                   "SymbolicCalls flags off)")
            if self._inert:
                return dr.zeros(mi.Color3f, dr.width(it.p))
            p = [mi.Float64(c) for c in it.p]
            if self.space == "object":
                p = self._in_object_frames(it, p, active)
            p = [wrap_far(c, dr.select, dr.round)
                 for c in apply_affine(self._world_to_texture, *p)]
            finite = dr.isfinite(p[0]) & dr.isfinite(p[1]) & dr.isfinite(p[2])
            p = [dr.select(finite, c, 0.0) for c in p]
            rgb = self._traced.colors(p, active & finite)
            return dr.select(active & finite, rgb, mi.Color3f(0.0))
        width = dr.width(it.p)
        # One kernel interleaves the points; in the LLVM variants NumPy then views Dr.Jit's
        # memory (DLPack). NumPy cannot view GPU memory: the CUDA variants copy the points.
        flat = dr.ravel(it.p, order="F")
        mask = mi.Bool(active) | dr.zeros(mi.Bool, width)
        dr.eval(flat, mask)
        host = np.from_dlpack(flat) if dr.backend_v(flat) == dr.JitBackend.LLVM else flat.numpy()
        points = host.reshape(width, 3)
        keep = mask.numpy()
        colors = np.zeros((width, 3), np.float32)
        if keep.all():
            colors[:] = self._query(points, it, keep)
        elif keep.any():
            colors[keep] = self._query(points[keep], it, keep)
        return mi.Color3f(colors.T)

    # -- traced lookups (driven by mitsuba_plugin.render and traced_renders) ------------

    def begin_tracing(self, scene: mi.Scene, own: bool = True) -> bool:
        """Serve symbolic ``eval`` calls in ``scene`` from the stored voxels; False, and
        nothing changed, when this texture cannot be traced (see the module
        documentation). A texture of another scene (not ``own``) that cannot be traced is
        traced inert instead, giving black: Dr.Jit traces every texture of the variant
        into a render's program, though no point of ``scene`` calls one of another scene."""
        if not dr.is_jit_v(mi.Float) or dr.backend_v(mi.Float) == dr.JitBackend.CUDA:
            return False  # CUDA: traced arithmetic is not bit-exact (module documentation)
        if self._traced is None:
            self._traced = TracedLookup(self.solid.store, self.filter, self._stand_in)
        if self.space == "object":
            # Taken now: a shape's matrix cannot be read inside a symbolic render. Another
            # scene's texture is read by no point of this one, its light's included.
            self._frames = _ObjectFrames(scene, self._emitting_shape(scene) if own else None)
        usable = self._traced.refresh()
        self._inert = not usable and not own
        self._tracing = threading.get_ident() if usable or self._inert else None
        return usable or self._inert

    @contextmanager
    def emitting_in(self, scene: mi.Scene) -> Iterator[None]:
        """In the block, read the points of no shape in the frame of the one shape whose
        area light this texture colours in ``scene`` (object space, where there is exactly
        one such shape): Mitsuba's area lights emit light tracing's rays (``ptracer``,
        ``sample_ray``) from points that carry none. Outside it, in world space, whatever
        was rendered before. :func:`mitsuba_plugin.render` renders in such a block; blocks
        may overlap (a preview rendered while a render goes on), the last leaving clears it."""
        with self._emitting_lock:
            if self._emitting == 0:
                self._emitter = self._emitting_shape(scene)
            self._emitting += 1
        try:
            yield
        finally:
            with self._emitting_lock:
                self._emitting -= 1
                if self._emitting == 0:
                    self._emitter = None

    def _emitting_shape(self, scene: mi.Scene) -> mi.Shape | None:
        if self.space != "object":
            return None
        lit = [shape for shape in scene.shapes() if shape.emitter() is not None
               and any(entry[2] is self
                       for entry in mi.traverse(shape.emitter()).properties.values())]
        return lit[0] if len(lit) == 1 else None

    def fill_misses(self) -> int:
        """Synthesize the bricks that traced lookups missed since the last call; returns
        how many voxels were logged (0: the last render read only stored voxels)."""
        misses = self._traced.take_misses()
        if len(misses):
            self.solid.store.prefetch(misses)
        return len(misses)

    def end_tracing(self) -> None:
        self._tracing = None

    def traced_stats(self) -> dict:
        """Symbolic renders with traced lookups, and how many of them missed a brick
        (those are rendered again)."""
        t = self._traced
        return {"renders": t.renders if t else 0,
                "renders_with_misses": t.renders_with_misses if t else 0}

    def scalar_stats(self) -> dict | None:
        """In scalar variants, the points served from the copies of bricks (``hits``) and
        left to the store (``misses``); None in the JIT variants."""
        return None if self._scalar is None else self._scalar.stats()

    def save(self) -> Path | None:
        """Write the brick store to the ``cache`` file, if one was given and the texture
        was not made to only read it (:func:`mitsuba_plugin.stores_read_only`)."""
        return self.solid.save() if self.cache is not None and not self._read_only else None

    def _scalar_color(self, it: mi.Interaction3f) -> list[float]:
        """RGB at the point of a scalar variant's interaction ``it``: from the mirrored
        bricks (:mod:`mitsuba_plugin.scalar`), else from the store, which synthesizes."""
        p = [float(c) for c in it.p]
        if self.space == "object":
            p = self._in_object_frames(it, p, True)
        point = apply_affine(self._world_to_texture, *p)
        if not all(map(math.isfinite, point)):  # before round(), which raises on them
            return [0.0, 0.0, 0.0]
        point = tuple(wrap_far(c, _choice_of, round) for c in point)
        color = self._scalar.color(point)
        if color is None:
            self._scalar.forget(point)
            return self._query_texture_space(np.array([point])).tolist()[0]
        return _as_rgb(np.array([color])).tolist()[0]  # float32, as Color3f rounds

    def _query(self, points: np.ndarray, it: mi.Interaction3f,
               keep: np.ndarray | None) -> np.ndarray:
        """RGB (N, 3) at scene ``points`` (N, 3) of interaction ``it``."""
        points = points.astype(np.float64)
        with np.errstate(invalid="ignore"):  # zero times infinity: NaN, filled black
            if self.space == "object":
                points = _to_object_space(points, it, keep, self._emitter)
            texture = apply_affine(self._world_to_texture, *points.T)
        return self._query_texture_space(np.stack(texture, axis=1))

    def _update_transform(self) -> None:
        placed = _affine_matrix(self.to_world)
        inverse = _inverse(placed)
        with np.errstate(over="ignore", invalid="ignore"):
            world_to_texture = inverse * np.array([[self.scale]] * 3 + [[1.0]])
        if not np.isfinite(world_to_texture).all():  # else every point would be black
            raise property_error(PLUGIN, "scale", f"{self.scale:g} times the inverse of "
                                 "to_world is beyond float64's range: lower scale or "
                                 "widen to_world")
        # Rows of plain floats: apply_affine runs on single points in scalar variants.
        self._world_to_texture = world_to_texture.tolist()
        self._placed = placed.astype(np.float32)


def _choice_of(condition: bool, if_true: float, if_false: float) -> float:
    """``select`` of one Python float, for :func:`wrap_far` in the scalar variants."""
    return if_true if condition else if_false


def _srgb_decoded(value: float) -> float:
    """:func:`~warptex.srgb.srgb_to_linear` of one Python float holding a float32 color,
    rounded to float32 by the caller's Color3f, for the scalar variants' one point per call,
    where a NumPy or Dr.Jit call (about 6 us) would cost as much as the lookup."""
    return srgb_decoded(value, _choice_of)


def _axis_colors(candidates: CandidateSet) -> list[np.ndarray]:
    """RGB (N, 3) of every pixel of each axis' exemplar (x, y, z), as stored: a voxel's
    color is the mean of one pixel of each (Dong 2008, section 4)."""
    return [_as_rgb(candidates.colors[k].reshape(-1, candidates.channels))
            for k in candidates.axis_source]


def _voxel_color_range(axes: list[np.ndarray],
                       decode: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mean RGB of the voxels of exemplars ``axes`` (:func:`_axis_colors`) and bounds
    below and above on their channels, as eval gives them (decoded from sRGB where
    ``decode``): each axis weighs the same, whatever its size, and a voxel's three pixels
    are averaged before they are decoded. The mean is estimated on a fixed sample of pixel
    triples; the bounds are exact, since a voxel averages its pixels in the same float32
    order, and filtering only mixes voxels."""
    low, high = ((f(axes[0], axis=0) + f(axes[1], axis=0) + f(axes[2], axis=0)) / np.float32(3)
                 for f in (np.min, np.max))
    if not decode:
        return np.mean([a.mean(axis=0, dtype=np.float64) for a in axes], axis=0), low, high
    rng = np.random.default_rng(0)
    triples = [a[rng.integers(len(a), size=_MEAN_SAMPLES)] for a in axes]
    voxels = (triples[0] + triples[1] + triples[2]) / np.float32(3)
    return (srgb_to_linear(voxels).mean(axis=0, dtype=np.float64), srgb_to_linear(low),
            srgb_to_linear(high))


def _as_rgb(colors: np.ndarray) -> np.ndarray:
    """(N, 3) float32 from (N, C) colors: gray is repeated, extra channels dropped."""
    if colors.shape[1] >= 3:
        return np.ascontiguousarray(colors[:, :3], np.float32)
    return np.repeat(colors[:, :1], 3, axis=1).astype(np.float32)


def _to_object_space(points: np.ndarray, it: mi.Interaction3f, keep: np.ndarray | None,
                     emitter: mi.Shape | None = None) -> np.ndarray:
    """``points`` taken into the frame of the instance each was found on, else of its
    shape when the shape has a ``to_world`` parameter, else, for points of no shape (an
    area light's, as light tracing emits them), of ``emitter``; unchanged otherwise.

    ``keep`` marks the JIT lanes that ``points`` hold, None under the scalar variants.
    """
    if keep is None:  # the scalar variants: one point, on one object at most; no masks
        for obj in (it.instance, emitter if it.shape is None else it.shape):
            to_object = None if obj is None else _to_object_matrix(obj)
            if to_object is not None:
                return np.stack(apply_affine(to_object.tolist(), *points.T), axis=1)
        return points
    out = points.copy()
    placed = np.zeros(len(points), bool)
    for pointers, shapeless in ((it.instance, None), (it.shape, emitter)):
        for rows, obj in _objects(pointers, keep):
            obj = shapeless if obj is None else obj
            to_object = None if obj is None else _to_object_matrix(obj)
            rows &= ~placed
            if to_object is not None and rows.any():
                out[rows] = np.stack(apply_affine(to_object.tolist(), *points[rows].T), axis=1)
                placed |= rows
    return out


def _objects(pointers: Any, keep: np.ndarray) -> list[tuple[np.ndarray, Any]]:
    """The distinct objects behind shape ``pointers`` at the ``keep`` lanes, each with
    the mask of the kept lanes that point to it; None for the lanes of a null pointer."""
    ids = np.broadcast_to(dr.reinterpret_array(mi.UInt32, pointers).numpy(), keep.shape)
    kept = ids[keep]
    unique, first = np.unique(kept, return_index=True)
    lanes = np.flatnonzero(keep)[first]
    return [(kept == i, pointers[int(lane)] if i else None)
            for i, lane in zip(unique, lanes, strict=True)]


def _to_object_matrix(obj: mi.Object) -> np.ndarray | None:
    """The inverse of the object's ``to_world`` matrix, if it exposes one that can be
    inverted: a degenerate shape (a sphere of radius 0) has no frame, nor points to hit."""
    own = _OwnParameters(obj)
    obj.traverse(own)
    to_world = own.value("to_world")
    return None if to_world is None else _finite_inverse(_affine_matrix(to_world))


class _OwnParameters(mi.TraversalCallback):
    """An object's own parameters as ``mi.traverse`` reads them, its children (a shape's
    BSDF, its textures, this plugin's among them) left alone: ``mi.traverse`` walks the whole
    subtree, which the scalar variants paid at every shading point in object space (4-5x
    the time of world space)."""

    def __init__(self, obj: mi.Object) -> None:
        super().__init__()
        self._obj = obj
        self._values: dict[str, tuple[Any, Any]] = {}

    def put(self, name: str, value: Any, flags: int, cpptype: Any = None) -> None:
        if not isinstance(value, mi.Object):
            self._values[name] = (value, cpptype)

    def value(self, name: str) -> Any:
        """Parameter ``name``, or None where the object has none."""
        if name not in self._values:
            return None
        value, cpptype = self._values[name]
        return value if cpptype is None else mi.get_property(value, cpptype, self._obj)


def _shape_id(shape: mi.Shape) -> int:
    """The registry id that a shape pointer to ``shape`` holds in the JIT variants."""
    return int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])


class _ObjectFrames:
    """:func:`_to_object_space` inside a traced program: the world-to-object matrix of
    each top-level shape of a scene that has a frame (instances, shapes with a
    ``to_world`` parameter), found per lane through the shape pointers' registry ids, and
    ``emitter``'s for the lanes of no shape."""

    def __init__(self, scene: mi.Scene, emitter: mi.Shape | None = None) -> None:
        framed = [(_shape_id(s), _to_object_matrix(s)) for s in scene.shapes()]
        framed = [(i, m) for i, m in framed if m is not None]
        index = np.full(max([i for i, _ in framed], default=0) + 1, -1, np.int32)
        matrices = np.zeros((max(len(framed), 1), 12))
        for n, (i, to_object) in enumerate(framed):
            index[i] = n
            matrices[n] = to_object[:3].reshape(-1)
        at = -1 if emitter is None else _shape_id(emitter)
        self._emitter = int(index[at]) if 0 <= at < len(index) else -1
        self._index = mi.Int32(index)
        self._matrices = mi.Float64(matrices.reshape(-1))

    def to_object(self, it: mi.Interaction3f, p: list[mi.Float64]) -> list[mi.Float64]:
        """World points ``p`` of interaction ``it`` in the frame of the instance each
        was found on, else of its shape when that has one; unchanged otherwise."""
        size = dr.opaque(mi.UInt32, dr.width(self._index))
        frame = mi.Int32(-1)
        for pointers in (it.instance, it.shape):
            ids = dr.reinterpret_array(mi.UInt32, pointers)
            found = dr.gather(mi.Int32, self._index, ids, ids < size)
            frame = dr.select((frame < 0) & (ids < size), found, frame)
        if self._emitter >= 0:  # a point of no shape: emitted from an area light
            frame = dr.select(dr.reinterpret_array(mi.UInt32, it.shape) == 0,
                              mi.Int32(self._emitter), frame)
        placed = frame >= 0
        at = mi.UInt32(dr.maximum(frame, 0)) * 12
        m = [dr.gather(mi.Float64, self._matrices, at + k, placed) for k in range(12)]
        moved = apply_affine([m[0:4], m[4:8], m[8:12]], *p)
        return [dr.select(placed, q, c) for q, c in zip(moved, p, strict=True)]
