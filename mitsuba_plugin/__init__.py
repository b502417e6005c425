"""Mitsuba 3 plugins that evaluate warptex solid textures lazily at shading points.

``register()`` adds, for the current Mitsuba variant (any: RGB, spectral or monochrome;
``use_variant()`` sets one and says what it lacks here), the texture ``lazy_solid``
(:mod:`mitsuba_plugin.texture`) and the medium ``lazy_solid_medium``
(:mod:`mitsuba_plugin.volume`). ``render()`` renders a scene so that every voxel it
shows was synthesized (see :mod:`mitsuba_plugin.traced`)::

    import warptex  # first: points Dr.Jit at a usable libLLVM
    import mitsuba as mi
    import mitsuba_plugin

    mitsuba_plugin.set_best_variant()
    mitsuba_plugin.register()
    scene = mi.load_file("scenes/bunny_wood.xml")
    image = mitsuba_plugin.render(scene, spp=16)
    mitsuba_plugin.save_caches(scene)  # the brick stores of its textures with a ``cache`` file

Under the JIT variants a symbolic render traces every live BSDF, so while a
``lazy_solid`` texture is alive in the process, render through ``render()``, in
``wavefront()`` mode, or inside a ``traced_renders()`` block (your own ``mi.render`` calls
with parameters and gradients, once ``render()`` has stored what they read); a plain
symbolic ``mi.render`` raises rather than show voxels that were never synthesized.
"""

from __future__ import annotations

import importlib
import threading
import warnings
import weakref
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, ExitStack, contextmanager
from pathlib import Path

import drjit as dr
import mitsuba as mi

import warptex
from mitsuba_plugin import properties
from warptex.llvm import MIN_LLVM_MAJOR, configure_drjit
from warptex.settings import MAX_SPP, is_integer

# Symbolic renders of one batch before falling back to wavefront mode: each synthesizes
# what the previous one missed; paths seldom reach new bricks after the second.
TRACED_ROUNDS = 6
_registered: set[str] = set()
# One traced render at a time: textures keep one miss log each.
_tracing = threading.Lock()
_tracer: list[int | None] = [None]  # the thread holding it
# Every lazy_solid texture alive, so a render helper can report and save brick stores;
# kept here because the plugin modules are re-run per variant.
live_textures: weakref.WeakSet = weakref.WeakSet()


def set_best_variant() -> str:
    """Set and return ``llvm_ad_rgb`` when LLVM works here, else ``scalar_rgb`` (with a
    warning where libLLVM was found but Dr.Jit could not start it)."""
    variant = warptex.best_mitsuba_variant()
    try:
        mi.set_variant(variant)
    except ImportError as e:
        warnings.warn(f"warptex: Mitsuba falls back to scalar_rgb: {variant} does not start "
                      f"({e})", stacklevel=2)
        variant = "scalar_rgb"
        mi.set_variant(variant)
    _exr_workers()
    return variant


def _exr_workers() -> None:
    """At least two Dr.Jit threads: Mitsuba's EXR writer and reader wait for ever for a
    worker of a pool Dr.Jit sizes to the cores, which one core leaves empty (a one-vCPU
    runner, a container pinned to one CPU; mitsuba3 issue #21)."""
    if dr.thread_count() < 2:
        dr.set_thread_count(2)


def use_variant(name: str) -> str:
    """Set and return Mitsuba variant ``name`` (``llvm_ad_spectral``, ``scalar_rgb``, ...);
    a ValueError says why this machine cannot run it, the variant set before kept."""
    if name not in mi.variants():
        raise ValueError(f"unknown Mitsuba variant {name!r}; this Mitsuba has "
                         f"{', '.join(mi.variants())}")
    if name.startswith("llvm_") and configure_drjit() is None:
        raise ValueError(f"Mitsuba variant {name} needs libLLVM >= {MIN_LLVM_MAJOR} (install "
                         "libllvm19 or set DRJIT_LIBLLVM_PATH); scalar_* variants need none")
    previous = mi.variant()
    try:
        mi.set_variant(name)
    except ImportError as e:  # no usable GPU, or a libLLVM Dr.Jit cannot start
        if previous is not None:  # Mitsuba is left without a variant otherwise
            mi.set_variant(previous)
        if name.startswith("cuda_"):
            raise ValueError(f"Mitsuba variant {name} needs a CUDA GPU and its driver, which "
                             f"Dr.Jit does not find here ({e})") from None
        raise ValueError(f"Mitsuba variant {name} does not start here ({e})") from None
    _exr_workers()
    return name


def register() -> None:
    """Register ``lazy_solid`` and ``lazy_solid_medium`` for the current variant.

    Mitsuba keeps plugins per variant and a Python plugin subclasses that variant's
    ``mi.Texture``, so, like Mitsuba's own Python plugins, the plugin modules are
    (re-)run for each new variant. Calling again for the same variant registers nothing
    again. Dr.Jit gets the two threads Mitsuba's EXR files need (``_exr_workers``).
    """
    variant = mi.variant()
    if variant is None:
        raise RuntimeError("mitsuba_plugin.register: set a Mitsuba variant first "
                           "(mitsuba_plugin.set_best_variant())")
    _exr_workers()  # a variant set by mi.set_variant, as scripts do, left it unchecked
    properties.note_resolver_outside_a_parse()
    if variant in _registered:
        return
    from mitsuba_plugin import texture, volume

    texture = importlib.reload(texture)
    volume = importlib.reload(volume)
    mi.register_texture(texture.PLUGIN, texture.LazySolidTexture)
    mi.register_medium(volume.MEDIUM, volume.lazy_solid_medium)
    _registered.add(variant)


# How lazy_solid textures made now behave, set for scenes loaded in a block (below).
_loading: dict[str, bool | None] = {
    "candidates_bar": None,  # None: a bar in a terminal only
    "stores_read_only": False,
}


@contextmanager
def _while_loading(setting: str, value: bool) -> Iterator[None]:
    before, _loading[setting] = _loading[setting], value
    try:
        yield
    finally:
        _loading[setting] = before


def candidates_progress() -> AbstractContextManager[None]:
    """Show the bar of the candidates that ``lazy_solid`` textures pre-compute while scenes
    load in this block also where stderr is a log (a terminal shows it anyway), as
    ``warptex render`` does: a new exemplar may take minutes."""
    return _while_loading("candidates_bar", True)


def candidates_bar() -> bool | None:
    """Whether candidates pre-computed now show their bar (``precompute``'s ``progress``)."""
    return _loading["candidates_bar"]


def stores_read_only() -> AbstractContextManager[None]:
    """``lazy_solid`` textures of scenes loaded in this block only read their ``cache``
    files, as ``warptex render --read-only-stores`` does: their ``save()`` writes nothing,
    and a file yet to be made in a place that cannot be written is no error (a shared
    folder not filled yet); the render starts without one."""
    return _while_loading("stores_read_only", True)


def stores_are_read_only() -> bool:
    """Whether textures made now only read their ``cache`` (:func:`stores_read_only`)."""
    return bool(_loading["stores_read_only"])


@contextmanager
def wavefront() -> Iterator[None]:
    """Dr.Jit's ``SymbolicLoops`` and ``SymbolicCalls`` off for the duration.

    Mitsuba then runs each bounce and each BSDF/medium call as its own kernel on
    concrete arrays (wavefront mode), so the plugins can hand whole batches of points
    to Warp. The flags are restored afterwards.
    """
    flags = (dr.JitFlag.SymbolicLoops, dr.JitFlag.SymbolicCalls)
    saved = [dr.flag(f) for f in flags]
    try:
        for f in flags:
            dr.set_flag(f, False)
        yield
    finally:
        for f, value in zip(flags, saved, strict=True):
            dr.set_flag(f, value)


def first_sensor(scene: mi.Scene) -> mi.Sensor:
    """The sensor ``render`` renders from, or ValueError for a scene without one."""
    sensors = scene.sensors()
    if not sensors:
        raise ValueError("the scene has no sensor (camera) to render from")
    return sensors[0]


def render(scene: mi.Scene, spp: int | None = None, batches: int = 1, seed: int = 0,
           progress: Callable[[int, int], None] | None = None) -> mi.TensorXf:
    """Render ``scene``: ``batches`` renders of ``spp / batches`` samples (with different
    seeds) averaged, calling ``progress(done, batches)`` before the first and after each.
    A sampler that stratifies its samples (every one of Mitsuba's but ``independent``)
    renders them in one batch, whose stratification then spans them all.

    Each batch is rendered in Mitsuba's symbolic mode with the textures' lookups traced,
    again after synthesizing what it missed, and kept only once it missed nothing; after
    ``TRACED_ROUNDS`` tries, or when a texture cannot be traced, it is rendered in
    wavefront mode, where every lookup synthesizes what it lacks. Either way each color
    is the stored voxel's, so the image does not depend on the mode.

    ``spp`` (default: the scene's sampler's count) and ``batches`` are positive integers;
    an ``spp`` that the sampler would round (a stratified one takes squares) is refused.
    Batch ``i`` samples with the seed ``seed * batches + i``, which Mitsuba keeps in 32
    bits. The scene's sampler keeps its sample count.
    """
    _check_scene(scene, whole=True)
    _check_texture_places(scene)
    for name, value in (("spp", spp), ("batches", batches), ("seed", seed)):
        if value is not None and not is_integer(value):
            raise TypeError(f"{name} must be an integer, got {value!r}")
    sampler = first_sensor(scene).sampler()
    shares = _batch_shares(sampler, spp, batches)
    total, batches = sum(shares), len(shares)
    if not 0 <= seed * batches + batches - 1 < 2**32:
        raise ValueError(f"seed must be 0 to {2**32 // batches - 1} for {batches} "
                         f"batch{'es' if batches > 1 else ''}, got {seed}")
    image = None
    if progress is not None:
        progress(0, batches)
    kept = sampler.sample_count()  # each batch sets it to its share
    with ExitStack() as emitting:
        for texture in textures(scene):
            emitting.enter_context(texture.emitting_in(scene))
        try:
            for i, share in enumerate(shares):
                part = _render_batch(scene, share, seed * batches + i)
                weighted = part * (share / total)
                image = weighted if image is None else image + weighted
                dr.eval(image)
                if progress is not None:
                    progress(i + 1, batches)
        finally:
            sampler.set_sample_count(kept)
    return image


def _batch_shares(sampler: mi.Sampler, spp: int | None, batches: int) -> list[int]:
    """Samples per pixel of each batch of a render of ``spp`` samples (default: the
    sampler's count) in at most ``batches``: one batch unless ``sampler`` takes any count
    as it is (a stratified one rounds 2 to 4 and would take more samples than its share,
    stratified batch by batch instead of across all). ValueError for an ``spp`` or
    ``batches`` that is not positive, or an ``spp`` the sampler would round."""
    total = spp if spp is not None else sampler.sample_count()
    if total < 1:
        raise ValueError(f"spp must be positive, got {total}" if spp is not None else
                         "the scene's sampler takes no samples per pixel: give spp")
    if total > MAX_SPP:
        raise ValueError(f"spp must be at most {MAX_SPP} (Mitsuba counts samples per pixel "
                         f"in 32 bits), got {total}")
    if batches < 1:
        raise ValueError(f"batches must be positive, got {batches}")
    kind = str(sampler).split("[", 1)[0]
    taken = _samples_taken(sampler, total)
    if taken != total:
        raise ValueError(f"{total} samples per pixel: the scene's {kind} takes {taken} when "
                         f"asked for {total}; ask for {taken}, or use another sampler")
    if kind != "IndependentSampler":
        batches = 1
    batches = min(batches, total)
    return [total // batches + (i < total % batches) for i in range(batches)]


def _samples_taken(sampler: mi.Sampler, count: int) -> int:
    """The samples per pixel ``sampler`` takes when asked for ``count``, found on a copy
    with Mitsuba's warning of the rounding held back."""
    trial, level = sampler.clone(), mi.log_level()
    mi.set_log_level(mi.LogLevel.Error)
    try:
        trial.set_sample_count(count)
    finally:
        mi.set_log_level(level)
    return trial.sample_count()


class MissedVoxels(RuntimeError):
    """Renders in a :func:`traced_renders` block read voxels that were not stored: they showed a
    stand-in color and are synthesized now, so the block is to be run again."""


@contextmanager
def traced_renders(scene: mi.Scene) -> Iterator[None]:
    """Symbolic renders of ``scene`` in the block, as your own code makes them: ``mi.render``
    with scene parameters, gradients and ``dr.backward`` (differentiable rendering with
    ``prb``, say), the ``lazy_solid`` textures' stored voxels traced into their programs.

    Render the scene once with :func:`render` first, so that what the block reads is
    stored, and keep ``dr.backward`` inside the block: a backward pass renders again.
    Render only ``scene`` in it: object-space textures find their frames among its
    shapes. Voxels the block reads that are not stored show a stand-in color; leaving the
    block synthesizes them and raises :class:`MissedVoxels`, and the gradients it left
    are of stand-in colors: clear them and run it again. Object-space textures take their
    shapes' frames as the block starts: move shapes between blocks. A texture that cannot
    be traced (a CUDA variant, bricks scattered too widely) is a RuntimeError: render in
    :func:`wavefront` mode then. Scalar variants need no block: any render works there.
    """
    if not dr.is_jit_v(mi.Float):
        yield
        return
    outcome: dict[str, int] = {}
    with _traced_lookups(scene, outcome) as usable:
        if not usable:
            raise RuntimeError("lazy_solid: a texture cannot be traced (a CUDA variant, or "
                               "stored bricks scattered too widely): render in "
                               "mitsuba_plugin.wavefront() mode instead")
        yield
    if outcome["missed"]:
        raise MissedVoxels(f"lazy_solid: the block's renders read {outcome['missed']} voxels "
                           "that were not stored, shown in a stand-in color; they are "
                           "synthesized now: run the block again")


@contextmanager
def _traced_lookups(scene: mi.Scene, outcome: dict[str, int]) -> Iterator[bool]:
    """Serve the live textures' symbolic evals in ``scene`` from their stored voxels for
    the block, which is told whether the scene's textures can be traced; on leaving, the voxels
    its renders missed are synthesized and counted in ``outcome["missed"]``."""
    if _tracer[0] == threading.get_ident():  # the lock would wait for this very thread
        raise RuntimeError("mitsuba_plugin: render() and traced_renders() cannot run "
                           "inside a traced_renders() block")
    # Every live texture, not only those traversal finds in the scene: Dr.Jit traces
    # every texture of the variant into the program, those of other scenes included (an
    # untraceable one of those is traced inert, not in the scene's way).
    live, own = textures(), {id(t) for t in textures(scene)}
    with _tracing:
        try:
            _tracer[0] = threading.get_ident()
            usable = all([t.begin_tracing(scene, own=id(t) in own) for t in live])
            yield usable
        finally:
            for t in live:
                t.end_tracing()
            _tracer[0] = None
        if usable:
            outcome["missed"] = sum(t.fill_misses() for t in live)


def _render_batch(scene: mi.Scene, spp: int, seed: int) -> mi.TensorXf:
    try:
        if dr.is_jit_v(mi.Float):
            image = _render_traced(scene, spp, seed)
            if image is not None:
                return image
        with wavefront():
            return mi.render(scene, spp=spp, seed=seed)
    except RuntimeError as e:
        # Dr.Jit wraps what escapes a custom operation, mi.render's included: a Ctrl-C
        # (or the commands' SIGTERM, a KeyboardInterrupt of theirs) during a render came as
        # this RuntimeError, which the stores' saving on a stop
        # (warptex.store_files.saved_when_stopped) and the commands' exit status did not see.
        if isinstance(e.__cause__, KeyboardInterrupt):
            raise e.__cause__ from None
        raise


def _render_traced(scene: mi.Scene, spp: int, seed: int) -> mi.TensorXf | None:
    """A render whose lookups all found stored voxels, or None (see :func:`render`)."""
    for _ in range(TRACED_ROUNDS):
        outcome: dict[str, int] = {}
        with _traced_lookups(scene, outcome) as usable:
            if not usable:
                return None
            image = mi.render(scene, spp=spp, seed=seed)
            dr.eval(image)
        if not outcome["missed"]:
            return image
    return None


def textures(scene: mi.Object | None = None) -> list:
    """The ``lazy_solid`` textures of ``scene`` (in its shapes' BSDFs, its media, nested
    or not), each once; without a scene, every one alive in this process. A medium that
    only an emitter names is not among them: Mitsuba does not traverse it, and no
    integrator looks it up."""
    if scene is None:
        return list(live_textures)
    _check_scene(scene)
    found = {id(texture): texture for _, texture in _texture_parameters(scene)}
    return list(found.values())


def _texture_parameters(scene: mi.Object) -> list[tuple[str, mi.Texture]]:
    """The parameters of ``scene`` that its ``lazy_solid`` textures own, by key, with
    their texture: each exposes its to_world, which finds it where it is nested."""
    return [(key, entry[2]) for key, entry in mi.traverse(scene).properties.items()
            if entry[2] in live_textures]


def _check_texture_places(scene: mi.Scene) -> None:
    """Refuse a ``lazy_solid`` that a constant volume of Mitsuba's own holds, as its own
    media (homogeneous, heterogeneous) hold a texture given for a volume: that volume reads
    the texture at p = 0 only (mitsuba_plugin.volume), so the medium would render one color
    without a word. Such a texture is the ``value`` of its volume in the scene's parameters."""
    for key, _ in _texture_parameters(scene):
        if key.endswith(".value.to_world"):
            where = ".".join(p for p in key.split(".")[:-2] if not p.startswith("object_"))
            raise ValueError(f"a lazy_solid texture is the constant volume {where} of a medium "
                             "of Mitsuba's own, which reads it at one point only: the medium "
                             "would show one color; use a lazy_solid_medium for its albedo or "
                             "sigma_t (README, The Mitsuba plugin)")


def _check_scene(scene: object, whole: bool = False) -> None:
    """Refuse what is not a loaded Mitsuba object (a scene's file name, say), or, where a
    ``whole`` scene is needed (to render it), not a scene: Mitsuba would answer either with
    an error of its own internals."""
    if isinstance(scene, mi.Scene if whole else mi.Object):
        return
    if type(scene).__name__ == "Scene" and type(scene).__module__ == "mitsuba":
        raise TypeError(f"scene was loaded under another Mitsuba variant than the current "
                        f"one, {mi.variant()}: load it again after mi.set_variant, or set "
                        "its variant back")
    raise TypeError(f"scene must be a loaded Mitsuba scene (mi.load_file, mi.load_dict), "
                    f"got {scene!r}")


def save_caches(scene: mi.Object | None = None) -> list[Path]:
    """Write the brick store of each ``lazy_solid`` texture of ``scene`` (without one, of
    every live texture) that has a ``cache`` file, as ``warptex render`` does after
    rendering, so that the next process starts from the voxels synthesized here; returns
    the store files, each of which then holds its texture's voxels (a file that holds them
    already, unchanged since it was loaded or saved, is not rewritten)."""
    return [path for texture in textures(scene) if (path := texture.save()) is not None]
