"""The settings a user chooses, their defaults and their ranges: those of synthesis (Dong
2008, section 5) and of lookups. A module of its own, free of the engine's imports, so that
commands and plugins can offer and check them before loading any kernels."""

from __future__ import annotations

import os
from numbers import Integral, Real
from pathlib import Path
from typing import Literal

import numpy as np

DEFAULT_JITTER = 1.0
MAX_JITTER = 64.0  # warp offsets stay far inside the int32 1/256-voxel arithmetic
DEFAULT_PASSES = 2  # the paper's (section 5.2)
# Each pass widens every level's dependency region (section 5.2), so time grows faster than
# the passes: one cold voxel costs 3,234 corrected voxels at 2 passes and 373,546 at 8.
MAX_PASSES = 8
MAX_SEED = 2**31 - 1  # the kernels hash seeds as 31-bit integers
RENDER_BATCHES = 8  # renders of one image at most (`warptex render`): each a step of its bar
# Batches take the sampler seeds seed * batches + i, which Mitsuba keeps as 32-bit integers.
MAX_SAMPLER_SEED = 2**32 // RENDER_BATCHES - 1
MAX_SPP = 2**32 - 1  # Mitsuba's samplers count samples per pixel in 32 bits
FILTERS = ("trilinear", "nearest")  # point lookups; the first is the default where one is offered
Filter = Literal["trilinear", "nearest"]
DEFAULT_CACHE_BYTES = 256 << 20  # synthesized voxels a brick store keeps in memory
DEFAULT_COARSE_CACHE_BYTES = 256 << 20  # coarse-level blocks the engine keeps per level
MIN_EXEMPLAR_SIZE = 16  # pixels a side: a pyramid of at least two levels of 5 x 5 patches
# Whether synthesis may continue an exemplar across its opposite edges, as commands and scenes
# write it (the first is the default), and the candidates' ``tileable`` parameter each means:
# decided from the photo (Exemplar.seams), the paper's tori, or no edge continued.
TILEABLE = {"auto": "auto", "yes": True, "no": False}


class SettingError(ValueError):
    """A synthesis setting out of range; ``name`` is the setting, ``problem`` the rest."""

    def __init__(self, name: str, problem: str) -> None:
        super().__init__(f"{name} {problem}")
        self.name = name
        self.problem = problem

    def __reduce__(self) -> tuple:
        # As a worker process raises it (warptex.compare): by default it would be rebuilt
        # from the message alone, and the parent's pool would break instead.
        return type(self), (self.name, self.problem)


class SettingTypeError(SettingError, TypeError):
    """A synthesis setting of the wrong type (a float for an integer, a string for a flag):
    a SettingError, as every refused setting is, and a TypeError, as Python's own functions
    and warptex's other arguments raise for one."""


def check_settings(jitter: float = DEFAULT_JITTER, passes: int = DEFAULT_PASSES,
                   seed: int = 0) -> None:
    """Raise SettingError unless ``jitter``, ``passes`` and ``seed`` are within what the
    engine supports: the user-facing settings of :class:`warptex.synthesis.Synthesizer`."""
    for name, value, kind in (("seed", seed, Integral), ("passes", passes, Integral),
                              ("jitter", jitter, Real)):
        if isinstance(value, bool) or not isinstance(value, kind):
            noun = "an integer" if kind is Integral else "a number"
            raise SettingTypeError(name, f"must be {noun}, got {value!r}")
    if not 0 <= seed <= MAX_SEED:
        raise SettingError("seed", f"must be within [0, {MAX_SEED}], got {seed}")
    if not 0.0 <= jitter <= MAX_JITTER:
        raise SettingError("jitter", f"must be within [0, {MAX_JITTER:g}], got {jitter}")
    if not 0 <= passes <= MAX_PASSES:
        raise SettingError("passes", f"must be within [0, {MAX_PASSES}], got {passes}")


def is_integer(value: object) -> bool:
    """Whether ``value`` is an integer (Python's or NumPy's) and not a bool, which Python
    counts as one: ``size=True`` is a mistake, not 1."""
    return isinstance(value, Integral) and not isinstance(value, bool)


def check_count(name: str, value: object, low: int = 0) -> int:
    """``value`` as an int, after a SettingError unless it is an integer of at least ``low``
    (a count or a number of bytes; a bool or a float is refused, not truncated)."""
    if not is_integer(value):
        raise SettingTypeError(name, f"must be an integer, got {value!r}")
    if value < low:
        raise SettingError(name, f"must be at least {low}, got {value}")
    return int(value)


def check_flag(name: str, value: object) -> bool:
    """``value`` after a SettingError unless it is a bool ("no" would count as true)."""
    if not isinstance(value, bool | np.bool_):
        raise SettingTypeError(name, f"must be True or False, got {value!r}")
    return bool(value)


def check_tileable(value: object) -> bool | str:
    """``value`` as the ``tileable`` parameter (``"auto"``, True or False), after a TypeError
    or ValueError unless it is one of them."""
    if not isinstance(value, bool | np.bool_ | str):
        raise TypeError(f'tileable must be "auto", True or False, got {value!r}')
    if isinstance(value, str) and value != "auto":
        raise ValueError(f'tileable must be "auto", True or False, got {value!r}')
    return value if isinstance(value, str) else bool(value)


def check_file_name(name: str, value: object) -> Path:
    """``value`` as a Path, after a TypeError naming ``name`` unless it is a file name (str
    or path-like): pathlib's own error names no argument."""
    if not isinstance(value, str | os.PathLike):
        raise TypeError(f"{name} must be a file name (str or Path), got {value!r}")
    return Path(value)


def names_folder(text: str) -> bool:
    """Whether a file name, as given, names a folder: it ends in a slash, ``.`` or ``..``,
    which Path would drop or keep as a name to write a file under."""
    return os.path.basename(text) in ("", ".", "..")


def tileable_word(value: bool | str) -> str:
    """The word commands and scenes write for the ``tileable`` parameter ``value``."""
    value = check_tileable(value)
    return next(word for word, meaning in TILEABLE.items() if meaning == value)


def check_max_size(max_size: int | None) -> None:
    """Raise SettingError unless ``max_size``, the larger side an exemplar is shrunk to when
    loaded (``Exemplar.load``), is None or an integer of at least MIN_EXEMPLAR_SIZE."""
    if max_size is None:
        return
    if not is_integer(max_size):
        raise SettingTypeError("max_size", f"must be an integer, got {max_size!r}")
    if max_size < MIN_EXEMPLAR_SIZE:
        raise SettingError("max_size", f"must be at least {MIN_EXEMPLAR_SIZE} pixels, got "
                           f"{max_size}")
