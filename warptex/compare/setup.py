"""What a comparison of solid texture methods runs with and what it returns (Dong 2008,
6.3-6.4): the :class:`Setup` of exemplars and settings that every method shares, one
:class:`MethodResult` per method, and their :class:`Comparison`."""

from __future__ import annotations

import warnings
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path

import numpy as np

from warptex.exemplar import (
    AlphaDropped,
    Exemplar,
    ExemplarError,
    axis_triple,
    check_same_channels,
    srgb_encoded,
)
from warptex.settings import (
    DEFAULT_JITTER,
    DEFAULT_PASSES,
    check_count,
    check_file_name,
    check_flag,
    check_max_size,
    check_settings,
    check_tileable,
)
from warptex.thread_warnings import captured

MIN_SIZE = 8  # the measures read 5 x 5 patches of slices every 2 voxels


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
    x axis and, where given, of y and z (:meth:`paths`; files given as str are kept as
    Path, as the annotations say once it is made); the volume's edge; the seed of every
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
