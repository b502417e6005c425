"""A comparison's report (Dong 2008, 6.3-6.4, whose Fig. 8, 11 and 12 set methods side by
side): the picture sheet, the score table in Markdown and JSON, and what they say of the
machine, the versions, the settings and the measures that the numbers come from."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np

from warptex import metrics
from warptex.archive import file_problem, iso_date, one_file_twice, write_together
from warptex.compare.methods import _KOPF, _LAZY, _edge, _engine_device, _middle
from warptex.compare.setup import Axes, Comparison, MethodResult, Setup, _distinct
from warptex.exemplar import Exemplar
from warptex.settings import DEFAULT_JITTER, DEFAULT_PASSES, tileable_word
from warptex.srgb import reencoded

REPORT_FILES = ("sheet.png", "table.md", "table.json")  # what write_report writes
# Of table.json; 2: format, axes, passes, exemplar max size and digest; 3: pre-computation
# seconds, device memory, the settings of the methods and measures, more versions; 4: the
# exemplar of each axis, the lazy engine's jitter and shifted tiles as run; 5: repetition
# counts peaks of the autocorrelation only; 6: tiled's pre-computation seconds are null (it
# reads the candidates that lazy computed).
TABLE_FORMAT = 6
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
