"""``warptex render``: render a Mitsuba scene that uses ``lazy_solid`` and report the stores.

Kept beside the plugin so ``warptex.cli`` only parses arguments; Mitsuba is imported on
use, so the other subcommands stay light.
"""

from __future__ import annotations

import contextlib
import json
import re
import sys
import tempfile
import time
import xml.etree.ElementTree as ElementTree
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, NotRequired, TypedDict

from warptex.archive import (
    endings,
    file_problem,
    file_state,
    iso_date,
    overwritten_input,
    write_failure,
    write_together,
)
from warptex.machine import software_versions
from warptex.settings import MAX_SAMPLER_SEED, MAX_SPP, RENDER_BATCHES
from warptex.stops import deferred_stops
from warptex.store_files import StoreFileError, saved_and_said, saved_if_any, saved_when_stopped
from warptex.warp_runtime import KernelCacheError

if TYPE_CHECKING:
    from warptex.store import StoreStats

IMAGE_SUFFIXES = (".exr", ".png")
# Of the report beside the image (<output>.json); 2: format, date, versions, sampler seed,
# scene parameters, and each texture's properties as a mapping beside its string.
REPORT_FORMAT = 2
# Arguments of mi.load_file, which its keyword arguments (scene parameters) cannot be.
_LOAD_FILE_ARGUMENTS = ("path", "parallel", "optimize")


class TextureReport(TypedDict):
    """What a render's report says of one ``lazy_solid`` texture of the scene."""

    texture: str  # the texture as Mitsuba prints it
    properties: dict  # LazySolidTexture.properties(): what sets the colors a point shows
    store: StoreStats
    traced: dict[str, int]  # symbolic renders with traced lookups, and those that missed
    scalar: dict[str, int] | None  # scalar variants' lookups from brick copies; None in JIT
    saved_to: str | None  # the store file written or left as it was; None: not saved
    store_file: str | None  # "written", or "unchanged" where the file held every voxel
    not_saved: NotRequired[str]  # why the store file could not be written


class RenderReport(TypedDict):
    """What :func:`render_scene` returns and writes beside the image (``<output>.json``)."""

    format: int  # REPORT_FORMAT
    scene: str
    image: str
    date: str  # ISO 8601, UTC
    versions: dict[str, str]  # warptex.machine.software_versions()
    variant: str
    size: list[int]  # width, height
    spp: int
    sampler_seed: int
    parameters: dict[str, str | int]  # the scene's parameters, $width and $height included
    load_seconds: float
    render_seconds: float
    textures: list[TextureReport]


class OutputError(Exception):
    """A file the render writes at its end (image, statistics, a brick store) that could not
    be written, though the scene was fine: a full disk, a lost mount."""


def _samples_per_batch(total: int) -> int:
    """The most samples per pixel one of the batches of a ``total``-sample render holds."""
    return -(-total // min(RENDER_BATCHES, total))


def parse_resolution(text: str) -> tuple[int, int]:
    """``"WxH"`` as (width, height), both positive."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--res must look like 256x256, got {text!r}") from None
    if width < 1 or height < 1:
        raise ValueError(f"--res must be positive, got {text!r}")
    return width, height


def _check_render_size(width: int, height: int, samples: int) -> None:
    """Refuse, before rendering, a batch of ``samples`` per pixel that Dr.Jit's arrays
    (at most 2^32 entries) cannot hold. Memory is not estimated: a traced render keeps a
    sample's path in registers, a wavefront one in arrays, and the mode is chosen later."""
    what = f"{width}x{height} pixels at {samples} samples per pixel in a batch"
    # The film keeps up to 5 values per pixel (RGB, alpha, weight); a wavefront one per sample.
    if width * height * max(samples, 5) >= 2**32:
        raise ValueError(f"{what} exceed Mitsuba's arrays of at most 2^32 entries; lower "
                         "--res or --spp")


def _scene_error(text: str, scene: Path | None = None) -> str:
    """Mitsuba's message for ``scene`` failing to load, as one line for a user.

    A plugin written in Python that raises while it is constructed (``lazy_solid`` checking
    its properties) reaches Mitsuba's parser as a whole Python traceback; only where in the
    scene and the exception's own message are kept. The place names its file when that is
    not ``scene`` itself (an ``<include>``d file).
    """
    # Each of Mitsuba's lines begins with its source's tag ("[parser.cpp:451] ").
    text = re.sub(r"^\[[\w.]+:\d+\] ", "", text.strip(), flags=re.MULTILINE)
    head, marker, trace = text.partition("Traceback (most recent call last):")
    if not marker:
        # An <include>d file's error comes wrapped once per file that includes it, a line
        # each, an include cycle's the same line fifteen times.
        lines = (line.strip() for line in text.splitlines())
        return " ".join(dict.fromkeys(line for line in lines if line))
    lines = trace.strip("\n").splitlines()
    frames = [i for i, line in enumerate(lines) if line.startswith(" ")]
    message = " ".join(lines[frames[-1] + 1 if frames else 0:]).strip()
    message = re.sub(r"^[A-Za-z_][\w.]*: ", "", message)
    where = re.match(r"At (.*) \((line \d+, col \d+)\)", head)
    if where is None:
        return message
    file, place = where.groups()
    if scene is not None and Path(file).resolve() == scene.resolve():
        return f"{place}: {message}"
    return f"{file} ({place}): {message}"


def _chain(error: BaseException) -> list[BaseException]:
    """``error`` and the exceptions it was raised from or while handling, outermost first."""
    chain = [error]
    while (cause := chain[-1].__cause__ or chain[-1].__context__) is not None:
        chain.append(cause)
    return chain


def _render_error(error: BaseException) -> str:
    """Mitsuba's own message for a render that failed: the first in the chain of ``error``
    that does not point elsewhere (Dr.Jit's wrapper says "see above"), without the tag of
    the class that raised it ("[Endpoint] ")."""
    own = next((str(e) for e in reversed(_chain(error)) if "(see above)" not in str(e)),
               str(error))
    return re.sub(r"^\[[\w.:]+\] ", "", own.strip())


def _kernel_cache_failure(error: RuntimeError) -> KernelCacheError | None:
    """The kernel cache's failure (the machine's, not the scene's) that Mitsuba's ``error``
    wraps, if any: as the exception itself (a render's) or as its traceback's text (a
    load's)."""
    wrapped = next((e for e in _chain(error) if isinstance(e, KernelCacheError)), None)
    if wrapped is not None:
        return wrapped
    found = re.search(r"^(?:[\w.]+\.)?KernelCacheError: (.+)$", str(error), re.MULTILINE)
    return None if found is None else KernelCacheError(found[1])


def _scene_root(path: Path) -> ElementTree.Element | None:
    """A scene file's XML; None where it does not parse, which loading it reports."""
    try:
        return ElementTree.parse(path).getroot()
    except (ElementTree.ParseError, OSError):
        return None


def _declared_parameters(root: ElementTree.Element | None) -> dict[str, str]:
    """The parameters a scene declares with ``<default name=... value=...>``, by name."""
    if root is None:
        return {}
    return {e.get("name"): e.get("value", "") for e in root.iter("default") if e.get("name")}


def scene_files(scene_path: Path, parameters: dict[str, str] | None = None) -> list[Path]:
    """The files a scene names (exemplars, meshes, included scenes and what they name, brick
    stores) that exist, looked up as Mitsuba does: beside the scene, else from the working
    folder; ``$name`` as the ``parameters`` given (``-D``) or the defaults of the scene and
    of the files including it set it, ``~`` as the home folder. A scene that does not parse
    names none; loading it reports why."""
    found: dict[Path, None] = {}
    read: set[Path] = set()
    given = {name: str(value) for name, value in (parameters or {}).items()}

    def existing(name: str) -> list[Path]:
        try:
            path = Path(name).expanduser()
        except RuntimeError:  # ~user of no such user: no file, which loading reports
            path = Path(name)
        places = (scene_path.parent / path, path)
        try:
            return [p for p in places if p.is_file()]
        except OSError:  # a value too long to be a file name, say
            return []

    def visit(path: Path, inherited: dict[str, str]) -> None:
        if path.resolve() in read:  # an include cycle; Mitsuba refuses it when loading
            return
        read.add(path.resolve())
        root = _scene_root(path)
        if root is None:
            return
        # A default never replaces a value set already (by an including file or -D).
        values = _declared_parameters(root) | inherited | given
        for element in root.iter():
            for value in (element.get("value"), element.get("filename")):
                if not value:
                    continue
                value = re.sub(r"\$(\w+)", lambda m: values.get(m.group(1), m.group(0)), value)
                if "$" in value:
                    continue
                files = existing(value)
                found.update(dict.fromkeys(files))
                if element.tag == "include" and files:
                    visit(files[0], values)

    visit(scene_path, {})
    return list(found)


def _saved_at_a_stop(scene) -> list[Path]:
    """The ``cache`` files of ``scene``'s textures, saved as a stop or a failure ends the
    render, but for stores that synthesized nothing (:func:`~warptex.store_files.saved_if_any`)."""
    import mitsuba_plugin

    return [path for texture in mitsuba_plugin.textures(scene)
            for path in saved_if_any(texture.solid.store, texture.cache, texture.save)]


def render_scene(scene_path: Path, output: Path, spp: int | None = None,
                 resolution: tuple[int, int] | None = None,
                 variant: str | None = None, save_stores: bool = True,
                 parameters: dict[str, str] | None = None, seed: int = 0) -> RenderReport:
    """Render ``scene_path`` to ``output`` (.exr or .png) with progress on stderr, save
    brick stores that have a ``cache`` file unless ``save_stores`` is False (stores that
    are only to be read, such as a shared one), and write their statistics as JSON beside
    the image (``<output>.json``). Returns that report. A render stopped by Ctrl-C or
    SIGTERM, or one Mitsuba fails half way, saves the stores too, before the
    KeyboardInterrupt or the error goes on.

    ``resolution`` sets the scene's ``$width``/``$height`` parameters, which the scenes
    in ``scenes/`` declare, and ``parameters`` any others, by name (Mitsuba's ``-D``).
    ``variant`` is the Mitsuba variant to render in (default:
    :func:`mitsuba_plugin.set_best_variant`'s). ``seed`` seeds the samples (renders of
    other seeds can be averaged).

    Raises ValueError for bad input, found before rendering, and :class:`OutputError` where
    a file cannot be written after it (the files are then left as they were, except that a
    brick store that cannot be written keeps neither the image nor its statistics from
    being written: it is entered there as ``not_saved``);
    :class:`~warptex.warp_runtime.KernelCacheError` where Warp's kernel cache cannot take
    or load a build.
    """
    parameters = _checked_arguments(output, spp, seed, resolution, parameters)
    statistics = output.with_name(output.name + ".json")
    _check_outputs(scene_path, parameters, output, statistics)
    if resolution is not None:  # before loading: a film this size may not even be made
        _check_render_size(*resolution, _samples_per_batch(spp or 1))
    variant = _started_variant(variant)
    import mitsuba_plugin

    params = parameters | ({} if resolution is None
                           else {"width": resolution[0], "height": resolution[1]})
    start = time.perf_counter()
    with _mitsuba_log_on_stderr():
        scene = _loaded_scene(scene_path, params, resolution, save_stores)
    loaded = time.perf_counter()
    shares = _checked_scene(scene, scene_path, spp, [output, statistics], save_stores)
    with (saved_when_stopped(partial(_saved_at_a_stop, scene) if save_stores else list),
          _mitsuba_log_on_stderr()):
        try:
            image = mitsuba_plugin.render(scene, spp=sum(shares), batches=len(shares),
                                          seed=seed, progress=_progress)
        except RuntimeError as e:  # what the scene asks of Mitsuba that it cannot do
            if save_stores:  # the voxels of the batches before are as good as any
                saved_and_said(partial(_saved_at_a_stop, scene), "the render failed")
            if (failure := _kernel_cache_failure(e)) is not None:
                raise failure from None
            raise ValueError(f"{scene_path}: Mitsuba cannot render the scene: "
                             f"{_render_error(e)}") from None
        rendered = time.perf_counter()
        # Before the image: a stop while the stores are written (the longest of the writes)
        # leaves the image and its statistics as they were, never one beside the other's.
        textures = [_save_and_report(t, save_stores) for t in mitsuba_plugin.textures(scene)]
    report: RenderReport = {
        "format": REPORT_FORMAT,
        "scene": str(scene_path),
        "image": str(output),
        "date": iso_date(),
        "versions": software_versions(),
        "variant": variant,
        "size": list(image.shape[1::-1]),
        "spp": sum(shares),
        "sampler_seed": seed,
        "parameters": params,
        "load_seconds": round(loaded - start, 3),
        "render_seconds": round(rendered - loaded, 3),
        "textures": textures,
    }
    _write_image_and_report(image, report, output, statistics)
    failed = [t["not_saved"] for t in textures if "not_saved" in t]
    if failed:  # the image is kept: a store is a cache, which the next render rebuilds
        raise OutputError("; ".join(failed))
    return report


def _checked_arguments(output: Path, spp: int | None, seed: int,
                       resolution: tuple[int, int] | None,
                       parameters: dict[str, str] | None) -> dict[str, str]:
    """The scene ``parameters`` (a copy), after a ValueError where the render's arguments
    are out of range or set one thing twice."""
    if output.suffix.lower() not in IMAGE_SUFFIXES:
        raise ValueError(f"output must end in {endings(IMAGE_SUFFIXES)}, got {output.name!r}")
    if spp is not None and not 1 <= spp <= MAX_SPP:
        raise ValueError(f"--spp must be 1 to {MAX_SPP} (Mitsuba counts samples per pixel in "
                         f"32 bits), got {spp}")
    if not 0 <= seed <= MAX_SAMPLER_SEED:
        raise ValueError(f"--sampler-seed must be 0 to {MAX_SAMPLER_SEED}, got {seed}")
    parameters = dict(parameters or {})
    if resolution is not None and {"width", "height"} & set(parameters):
        raise ValueError("--res sets the parameters width and height: give them with -D or "
                         "--res, not both")
    if spp is not None and "spp" in parameters:  # the render's count wins: -D would do nothing
        raise ValueError("--spp sets the samples per pixel, which scenes take as the parameter "
                         "spp: give it with -D or --spp, not both")
    reserved = sorted(set(parameters) & set(_LOAD_FILE_ARGUMENTS))
    if reserved:
        raise ValueError(f"-D {reserved[0]}: Mitsuba's load_file takes {reserved[0]} as an "
                         "argument of its own, so no scene parameter of that name can be set; "
                         "rename it in the scene")
    return parameters


def _check_outputs(scene_path: Path, parameters: dict[str, str], output: Path,
                   statistics: Path) -> None:
    """A ValueError where the image or its statistics would overwrite a file the scene
    reads, or cannot be written: before the minutes a render may take."""
    clash = overwritten_input([output, statistics],
                              [scene_path, *scene_files(scene_path, parameters)])
    if clash is not None:
        raise ValueError(f"{clash[0]}: would overwrite {clash[1]}, which the scene reads; "
                         "choose another output name")
    for written in (output, statistics):
        problem = file_problem(written)
        if problem is not None:
            beside = "" if written == output else f" (the statistics written with {output})"
            raise ValueError(f"{written}{beside}: {problem}")


def _started_variant(variant: str | None) -> str:
    """Mitsuba set to ``variant`` (the best this machine runs where None), with the
    plugin registered in it: the variant's name."""
    # A signal while Dr.Jit starts a variant's extension fails the import: it was taken for
    # a variant this machine cannot run (a scalar render, exit 0) or crashed the process.
    with deferred_stops():
        import mitsuba  # noqa: F401 (whole, before a stop can cut its import short)

        import mitsuba_plugin

        try:
            variant = (mitsuba_plugin.set_best_variant() if variant is None
                       else mitsuba_plugin.use_variant(variant))
        except ValueError as e:
            raise ValueError(f"--variant {variant}: {e}") from None
    mitsuba_plugin.register()
    return variant


def _loaded_scene(scene_path: Path, params: dict, resolution: tuple[int, int] | None,
                  save_stores: bool) -> object:
    """The scene of ``scene_path`` with its parameters ``params``, its textures' candidates
    pre-computed; Mitsuba's errors in the words of :func:`_load_failure`."""
    import mitsuba as mi

    import mitsuba_plugin

    try:
        reading = nullcontext() if save_stores else mitsuba_plugin.stores_read_only()
        with _status(f"loading {scene_path.name} (exemplars new to the candidate cache are "
                     "pre-computed first)"), mitsuba_plugin.candidates_progress(), reading:
            return mi.load_file(str(scene_path), **params)
    except RuntimeError as e:  # how Mitsuba reports parse and plugin errors, ours included
        raise _load_failure(e, scene_path, resolution) from None


def _load_failure(error: RuntimeError, scene_path: Path,
                  resolution: tuple[int, int] | None) -> BaseException:
    """What Mitsuba's ``error`` in loading ``scene_path`` is to the command: a stop, the
    kernel cache's failure, or a ValueError that names the parameter or the fault."""
    # Ctrl-C in a plugin that Mitsuba built on this thread comes wrapped, the Python
    # exception's own line last (the commands' SIGTERM is a KeyboardInterrupt of theirs,
    # which they tell apart by its signal); one on a loading thread arrives when loading
    # ends.
    if isinstance(error.__cause__, KeyboardInterrupt):
        return error.__cause__
    stop = r"^(?:[\w.]+\.)?(?:KeyboardInterrupt|SigtermInterrupt)\b"
    if re.search(stop, str(error), re.MULTILINE):
        return KeyboardInterrupt()
    if (failure := _kernel_cache_failure(error)) is not None:
        return failure
    unused = set(re.findall(r"^\s*- \$(\w+)=", str(error), re.MULTILINE))
    if resolution is not None and unused & {"width", "height"}:
        return ValueError(f"{scene_path}: --res sets the parameters $width and $height, "
                          "which this scene does not declare or does not use: add <default "
                          "name=\"width\" value=\"256\"/> and <integer name=\"width\" "
                          "value=\"$width\"/> in its film, the same for height")
    if unused:
        from mitsuba_plugin.properties import did_you_mean

        declared = _declared_parameters(_scene_root(scene_path))
        if len(unused) > 1:
            hint = ""
        elif unused <= set(declared):  # no typo to point at: the name is the scene's own
            hint = f" (declared by a <default>, but no value reads ${next(iter(unused))})"
        else:
            hint = did_you_mean(next(iter(unused)), tuple(declared))
        return ValueError(f"{scene_path}: -D sets parameters this scene does not use: "
                          f"{', '.join(sorted(unused))}{hint}")
    problem = _scene_error(str(error), scene_path)
    return ValueError(f"{scene_path}: cannot load the scene: {problem}")


def _checked_scene(scene: object, scene_path: Path, spp: int | None, outputs: list[Path],
                   save_stores: bool) -> list[int]:
    """The samples per pixel of each of the render's batches, after a ValueError naming
    ``scene_path`` where the scene cannot be rendered to ``outputs`` (the image, its
    statistics) as asked, or its textures' files are at fault."""
    import mitsuba_plugin

    try:
        sensor = mitsuba_plugin.first_sensor(scene)
        _check_renderable(scene, sensor, spp, outputs[0])
        mitsuba_plugin._check_texture_places(scene)
        for texture in mitsuba_plugin.textures(scene):
            _check_texture_files(texture, outputs, save_stores)
        shares = mitsuba_plugin._batch_shares(sensor.sampler(), spp, RENDER_BATCHES)
    except ValueError as e:
        raise ValueError(f"{scene_path}: {e}") from None
    _check_render_size(*sensor.film().crop_size(), max(shares))
    return shares


def _write_image_and_report(image: object, report: RenderReport, output: Path,
                            statistics: Path) -> None:
    """Write the image and its report together, and print the report; a stop meanwhile
    comes once the files are written and said to be, not between."""
    import mitsuba as mi

    text = json.dumps(report, indent=2) + "\n"
    with deferred_stops():
        try:
            # Synchronously: the default asynchronous write would race the rename.
            write_together([
                (output, lambda tmp: mi.util.write_bitmap(str(tmp), image, write_async=False)),
                (statistics, lambda tmp: tmp.write_text(text)),
            ])
        except OSError as error:
            raise OutputError(_write_failure(error, output)) from None
        _print_report(report)


def _write_failure(error: OSError, path: Path) -> str:
    """A write of ``path`` that failed after the render (a full disk, a lost mount), named
    after the file write_together was asked for."""
    return write_failure(error.filename or path, error)


def _check_renderable(scene, sensor, spp: int | None, output: Path) -> None:
    """Refuse a loaded scene that Mitsuba would fail to render, or to write to ``output``,
    only once it starts or ends, with an error from deep inside it: no integrator, an empty
    film, no samples (``spp``, where given, replaces the sampler's count), a film of more
    channels than a PNG holds."""
    if scene.integrator() is None:
        raise ValueError('the scene has no <integrator>: add one, such as <integrator '
                         'type="path"/>')
    aovs = scene.integrator().aov_names()
    channels = sensor.film().base_channels_count()
    if output.suffix.lower() == ".png" and (aovs or channels > 4):
        held = (f"arbitrary outputs ({', '.join(aovs)})" if aovs else f"{channels} channels")
        raise ValueError(f"{output}: the film holds {held}, more than a .png's RGB(A): write "
                         ".exr")
    width, height = sensor.film().crop_size()
    if width < 1 or height < 1:
        raise ValueError(f"the film is {width}x{height} pixels: give --res, or a positive "
                         "width and height in the scene or with -D")
    if spp is None and sensor.sampler().sample_count() < 1:
        raise ValueError("the sampler takes no samples per pixel (its sample_count is "
                         f"{sensor.sampler().sample_count()}): give --spp, or a positive "
                         "sample_count in the scene or with -D")


def _check_texture_files(texture, outputs: list[Path], saved: bool) -> None:
    """Refuse, before rendering, ``outputs`` that would overwrite a file the texture read
    (named through an include or a parameter, which :func:`scene_files` may miss), and a
    ``cache`` file that the render's end could not save: one this command writes as its
    image or statistics, or, where it is ``saved``, one in a place that cannot be written
    (the plugin accepts an existing store there, to read)."""
    read = [*texture.exemplars, *([texture.feature_mask] if texture.feature_mask else [])]
    clash = overwritten_input(outputs, read)
    if clash is not None:
        raise ValueError(f"{clash[0]}: would overwrite {clash[1]}, which a lazy_solid texture "
                         "reads; choose another output name")
    cache = texture.cache
    if cache is None:
        return
    for output in outputs:
        if cache.resolve() == output.resolve() or (
                cache.exists() and output.exists() and cache.samefile(output)):
            raise ValueError(f'lazy_solid: property "cache" names {output}, which this render '
                             "writes: choose another output name")
    problem = file_problem(cache) if saved else None
    if problem is not None:
        raise ValueError(f'lazy_solid: property "cache": the brick store would be saved to '
                         f"{cache} after rendering, which cannot be: {problem} (render with "
                         "--read-only-stores to only read it)")


@contextmanager
def _mitsuba_log_on_stderr() -> Iterator[None]:
    """Mitsuba's log lines of the block (its warnings) on stderr as it ends, uncoloured:
    Mitsuba writes them to stdout, coloured for a terminal even in a log, where a script
    reads the ``written:`` line. A file keeps them meanwhile, not a Python appender:
    Mitsuba calls its appenders under a lock, which one would hold while it waits for the
    GIL. Where no temporary folder can be made they go where Mitsuba sends them."""
    import mitsuba as mi
    from tqdm.auto import tqdm

    try:
        folder = tempfile.TemporaryDirectory(prefix="warptex-mitsuba-log-")
    except OSError:
        yield
        return
    with folder:
        log = Path(folder.name) / "mitsuba.log"
        logger = mi.logger()
        kept = [logger.appender(i) for i in range(logger.appender_count())]
        to_file = mi.StreamAppender(str(log))
        try:  # a stop between the two calls leaves Mitsuba's appenders as they were too
            logger.clear_appenders()
            logger.add_appender(to_file)
            yield
        finally:
            logger.clear_appenders()
            del to_file  # its last reference: the file is closed, every line in it
            for appender in kept:
                logger.add_appender(appender)
            with contextlib.suppress(OSError):
                for line in log.read_text(errors="replace").splitlines():
                    tqdm.write(line, file=sys.stderr)


@contextmanager
def _status(text: str) -> Iterator[None]:
    """``text`` on the terminal's last line while the block runs, then erased: a scene
    loads for seconds, a bar only where candidates are pre-computed. Not written where
    stderr is no terminal (logs), which show that bar alone."""
    shown = sys.stderr.isatty()
    if shown:
        print(text, end="", file=sys.stderr, flush=True)
    try:
        yield
    finally:
        if shown:
            print("\r\033[K", end="", file=sys.stderr, flush=True)


def _progress(done: int, total: int) -> None:
    # Redrawn in place as tqdm's bars are, so that in a log the command's stderr makes
    # lines of it as of theirs: the first, then at most one every few seconds, and the last.
    end = "\n" if done == total else ""
    print(f"\rrendering: batch {done}/{total}", end=end, file=sys.stderr, flush=True)


def _save_and_report(texture, save: bool) -> TextureReport:
    """The texture's entry of the report, its store saved first if ``save``; a store that
    cannot be written (a full disk) is entered as ``not_saved``, why, and left as it was."""
    saved, failed, before = None, None, None
    try:
        if save and texture.cache is not None:
            before = file_state(texture.cache)
        saved = texture.save() if save else None
    except OSError as error:
        failed = _write_failure(error, texture.cache)
    except StoreFileError as error:  # a file of another kind put there during the render
        failed = str(error)
    entry: TextureReport = {
        "texture": texture.to_string(), "properties": texture.properties(),
        "store": texture.solid.store.stats(),
        "traced": texture.traced_stats(), "scalar": texture.scalar_stats(),
        "saved_to": None if saved is None else str(saved),
        # A store that held every voxel already is left as it was (BrickStore.save).
        "store_file": None if saved is None else
        "unchanged" if before is not None and file_state(saved) == before else "written"}
    return entry if failed is None else entry | {"not_saved": failed}


def _print_report(report: RenderReport) -> None:
    print(f"written: {report['image']} ({report['size'][0]}x{report['size'][1]}, "
          f"{report['spp']} spp, {report['variant']}): load {report['load_seconds']:.1f} s, "
          f"render {report['render_seconds']:.1f} s")
    for entry in report["textures"]:
        s, t, c = entry["store"], entry["traced"], entry["scalar"]
        if c is not None:  # a scalar variant: points from brick copies, else the store
            lookups = (f"scalar lookups {c['hits']} from brick copies / {c['misses']} left "
                       "to the store, store lookups")
        else:
            lookups = (f"traced renders {t['renders']} (repeated after missing bricks: "
                       f"{t['renders_with_misses']}), wavefront lookups")
        print(f"  {entry['texture']}\n    {s['voxels']} voxels in {s['bricks']} bricks "
              f"({s['bytes'] / 2**20:.2f} MiB), {lookups} {s['hits']} hits / "
              f"{s['misses']} misses, synthesis {s['synthesis_seconds']:.1f} s (summed over "
              "the threads that synthesized)"
              + (f", saved to {entry['saved_to']}" if entry["store_file"] == "written" else
                 f", {entry['saved_to']} unchanged (it held them all)" if entry["saved_to"]
                 else ""))
    print(f"  statistics: {report['image']}.json")
