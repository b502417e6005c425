"""Properties of the warptex Mitsuba plugins: read once at load, each checked, and an
error that names the plugin and the property at fault (as Mitsuba's own plugins do)."""

from __future__ import annotations

import contextlib
import difflib
import stat
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import mitsuba as mi

# How a property of each kind is written in a scene, for errors that name the wrong one.
_KINDS = {int: 'an <integer ...>', float: 'a <float ...>', str: 'a <string ...>',
          bool: 'a <boolean ...>'}


class PropertyError(ValueError):
    """A property of a warptex plugin is missing or invalid."""


def property_error(plugin: str, name: str, problem: str) -> PropertyError:
    """The Mitsuba-style error, to raise, for property ``name`` of ``plugin``."""
    return PropertyError(f'{plugin}: property "{name}" {problem}')


def check_known(names: Iterable[str], known: tuple[str, ...], plugin: str) -> None:
    """Refuse a property ``plugin`` does not read, with the one it may be a typo of: Mitsuba
    would refuse it too, after the plugin's work, and name no likely one."""
    for name in names:
        if name not in known:
            raise unknown_property(plugin, name, known)


def unknown_property(plugin: str, name: str, known: tuple[str, ...]) -> PropertyError:
    """The error for property ``name``, which ``plugin`` does not read, naming the one of
    ``known`` it may be a typo of."""
    return property_error(plugin, name, f"is no property of {plugin}{did_you_mean(name, known)}")


def did_you_mean(name: str, known: tuple[str, ...]) -> str:
    """The hint at the one of ``known`` that ``name`` may be a typo of, or ""."""
    near = difflib.get_close_matches(name, known, n=1)
    return f'; did you mean "{near[0]}"?' if near else ""


def get_property(props: mi.Properties, name: str, kind: type, default: Any,
                 plugin: str) -> Any:
    """Property ``name`` converted to ``kind`` (int, float, str or bool), or ``default``."""
    if name not in props:
        return default
    value = props[name]
    if kind is float and isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
        got = (repr(value) if isinstance(value, int | float | str | bool)
               else f"a nested {type(value).__name__}")
        raise property_error(plugin, name, f"must be {_KINDS[kind]}, got {got}")
    return value


def choice_property(props: mi.Properties, name: str, options: tuple[str, ...],
                    plugin: str) -> str:
    """String property ``name``, one of ``options`` (the first is the default)."""
    value = get_property(props, name, str, options[0], plugin)
    if value not in options:
        allowed = " or ".join(f'"{o}"' for o in options)
        raise property_error(plugin, name, f'must be {allowed}, got "{value}"')
    return value


def scene_path(name: str, must_exist: bool) -> Path:
    """Absolute path of a file named in a scene (``~`` is the home folder).

    While Mitsuba parses a scene file its file resolver starts with the file's folder,
    so relative names resolve against the scene; ``mi.load_dict`` resolves against the
    working directory. A file to read (``must_exist``) is looked up in the resolver's
    other folders too, as Mitsuba looks up its own bitmaps; a file to write always goes
    in that first folder, so that it is never another scene's file found elsewhere, or,
    outside a parse, in the working folder (the resolver's first is the one Mitsuba
    started in, which a script may have left since).
    """
    path = Path(name).expanduser()
    resolver = mi.file_resolver()
    if must_exist:
        return Path(str(resolver.resolve(str(path)))).absolute()
    folders = _resolver_folders()
    kept = len(_OUTSIDE_A_PARSE)
    parsing = len(folders) > kept and folders[1:1 + kept] == _OUTSIDE_A_PARSE
    return (Path(folders[0]) / path if parsing else path).absolute()


# The file resolver's folders as :func:`note_resolver_outside_a_parse` found them, when
# the plugin was registered: a parse puts the scene's folder before them (even where they
# hold it already), and a script's own folders, appended since, come after them.
_OUTSIDE_A_PARSE: list[str] = []


def note_resolver_outside_a_parse() -> None:
    """Keep the file resolver's folders as they are now, outside any scene's parse."""
    _OUTSIDE_A_PARSE[:] = _resolver_folders()


def _resolver_folders() -> list[str]:
    """The folders Mitsuba's file resolver looks in, the scene's first while it parses one."""
    resolver = mi.file_resolver()
    return [str(resolver[i]) for i in range(len(resolver))]


def existing_scene_file(name: str, key: str, plugin: str) -> Path:
    """The file to read that property ``key`` names (:func:`scene_path`), or the error
    naming that property where there is none: as the exemplar reader tells them apart, a
    broken symbolic link or one that cannot be followed (a loop) is not a missing file."""
    path = scene_path(name, must_exist=True)
    try:
        mode = path.stat().st_mode
    except OSError:
        raise property_error(plugin, key, _missing_file(name)) from None
    if stat.S_ISDIR(mode):
        raise property_error(plugin, key, f'names a folder, not a file: "{name}"')
    if not stat.S_ISREG(mode):
        raise property_error(plugin, key, f'names no regular file (a pipe or a device): "{name}"')
    return path


def _missing_file(name: str) -> str:
    """Why ``name`` is no file in any folder the file resolver looks in (which takes a name
    it cannot follow for a missing one): the first place it cannot be looked up in, else a
    broken link, else that it exists nowhere."""
    path = Path(name).expanduser()
    folders = [] if path.is_absolute() else _resolver_folders()
    for place in [Path(folder) / path for folder in folders] or [path]:
        try:
            place.stat()
        except (FileNotFoundError, NotADirectoryError):  # a file on the way: none there either
            with contextlib.suppress(OSError):
                if place.is_symlink():
                    return f'names a broken symbolic link: "{name}" ({place})'
        except OSError as error:  # a folder on the way that cannot be searched, a link loop
            return f'cannot look up "{name}" ({place}: {error.strerror})'
    # The folder of a scene given by a bare file name is "", the working folder.
    shown = dict.fromkeys(f or "." for f in folders)  # a scene's folder may be listed twice
    searched = f" (looked for in {', '.join(shown)})" if folders else ""
    return f'names a file that does not exist: "{name}"{searched}'
