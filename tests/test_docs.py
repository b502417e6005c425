"""The pictures in docs/: the scripts that make them check their arguments before any work,
and the README links to each."""

from __future__ import annotations

import importlib.util
import json
import re
import shutil
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "docs" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("argv", [["--spp", "0"], ["--res", "0"], ["--res", "-3"]])
def test_make_renders_refuses_sizes_mitsuba_would_fail_on_deep_inside(argv, monkeypatch,
                                                                      capsys):
    make_renders = _script("make_renders")
    monkeypatch.setattr(sys, "argv", ["make_renders.py", *argv])
    with pytest.raises(SystemExit) as stop:
        make_renders.main()
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert f"error: {argv[0]} must be positive, got {argv[1]}" in err
    assert "Traceback" not in err


def test_readme_links_resolve_and_name_every_picture_in_docs():
    """Each relative link of README.md and scenes/README.md names a file that exists, and
    each picture the docs scripts and experiments made is linked from README.md."""
    links = {}
    for readme in (REPO / "README.md", REPO / "scenes" / "README.md"):
        for target in re.findall(r"\]\(([^)#\s]+)", readme.read_text()):
            if "://" not in target:
                links[(readme.parent / target).resolve()] = readme
    missing = [f"{readme.name}: {path}" for path, readme in links.items() if not path.exists()]
    assert missing == []
    pictures = sorted(p for folder in ("slices", "renders", "experiments")
                      for p in (REPO / "docs" / folder).glob("*.png"))
    assert pictures and [p for p in pictures if p.resolve() not in links] == []


def _run_make_comparisons(tmp_path, monkeypatch, result=None) -> list[bool]:
    """``docs/make_comparisons.py`` over the rosewood photo alone, writing under
    ``tmp_path``, with a ``compare`` of meaningless scores (or those ``result`` gives for a
    method and its correction passes) in no time and no reports written; the progress
    flags it passed to ``compare``."""
    from warptex.compare import Comparison, MethodResult

    if result is None:
        def result(method, passes):
            return MethodResult(method, [0.1] * 3, [0.2] * 3, [0.0] * 3, [0.0] * 3, 0.5, 1.0,
                                0.0, precompute_seconds=2.0)

    make_comparisons = _script("make_comparisons")
    photos = tmp_path / "photos"
    photos.mkdir()
    shutil.copy(REPO / "scenes" / "textures" / "wood_rosewood_64.png", photos)
    bars = []

    def compare(setup, methods, progress=True):
        bars.append(progress)
        return Comparison(setup, [result(m, setup.passes) for m in methods])

    monkeypatch.setattr(make_comparisons, "compare", compare)
    monkeypatch.setattr(make_comparisons, "write_report", lambda comparison, out: None)
    monkeypatch.setattr(make_comparisons, "HERE", tmp_path)
    (tmp_path / "comparisons").mkdir(exist_ok=True)
    monkeypatch.setattr(sys, "argv", ["make_comparisons.py", "--exemplars", str(photos)])
    make_comparisons.main()
    return bars


def test_make_comparisons_shows_its_progress_over_the_exemplars(tmp_path, monkeypatch,
                                                                capsys):
    """An hour's run: a bar over the exemplars, and compare's own bar of the methods; each
    exemplar's line of the index on stdout as it is measured."""
    bars = _run_make_comparisons(tmp_path, monkeypatch)
    out, err = capsys.readouterr()
    assert re.search(r"exemplars: 100%.*1/1", err)
    assert bars == [True, True]
    assert out.startswith("| [wood_rosewood](wood_rosewood/sheet.png) | 0.100 |")
    assert (tmp_path / "comparisons" / "README.md").read_text().endswith(out)


def test_make_comparisons_reports_each_method_s_worst_axis(tmp_path, monkeypatch):
    """The index's energies are the largest of the three axes', its bidirectional energies
    the largest of the axes' sums (an axis other than the worst energy's here, so not the
    sum of the two largest), and its ratios lazy over Kopf, as issue 7's bar reads them."""
    from warptex.compare import MethodResult

    scores = {  # energy and completeness per axis, seconds, repetition
        "lazy": ([0.30, 0.10, 0.20], [0.10, 0.50, 0.20], 0.5, 0.2),
        "lazy-3": ([0.12, 0.28, 0.20], [0.0] * 3, 0.75, 0.3),
        "kopf": ([0.10, 0.20, 0.25], [0.60, 0.10, 0.10], 10.0, 1.0),
        "kopf-meanshift": ([0.40, 0.20, 0.10], [0.0] * 3, 20.0, 1.0),
        "tiled": ([0.0] * 3, [0.0] * 3, 0.1, 0.9),
        "flat": ([0.05, 0.07, 0.06], [1.00, 0.90, 0.80], 0.1, 0.0),
    }

    def result(method, passes):
        name = "lazy-3" if passes == 3 else method
        energy, completeness, seconds, repetition = scores.get(name, ([0.0] * 3,) * 2
                                                               + (0.1, 0.0))
        return MethodResult(method, energy, completeness, [0.0] * 3, [0.0] * 3, repetition,
                            seconds, 0.0, precompute_seconds=2.0)

    _run_make_comparisons(tmp_path, monkeypatch, result)
    lines = (tmp_path / "comparisons" / "README.md").read_text().splitlines()
    header = next(line for line in lines if line.startswith("| exemplar |"))
    # Header and cell of each column after the exemplar's, in order ("lazy / kopf" twice).
    cells = list(zip([c.strip() for c in header.split("|")[2:-1]],
                     [c.strip() for c in lines[-1].split("|")[2:-1]], strict=True))
    assert cells == [
        ("lazy energy", "0.300"), ("kopf energy", "0.250"), ("lazy / kopf", "1.20"),
        ("kopf-ms energy", "0.400"), ("lazy / kopf-ms", "0.75"),
        ("lazy-3 energy", "0.280"), ("lazy-3 / kopf", "1.12"), ("flat energy", "0.070"),
        ("lazy bidirectional", "0.600"), ("kopf bidirectional", "0.700"),
        ("lazy / kopf", "0.86"), ("flat bidirectional", "1.050"),
        ("lazy s", "0.50"), ("lazy pre-computation s", "2.00"), ("kopf s", "10.0"),
        ("kopf-ms s", "20.0"), ("kopf / lazy time", "20"), ("kopf-ms / lazy time", "40"),
        ("lazy-3 s", "0.75"), ("lazy repetition", "0.200"), ("tiled repetition", "0.900")]


def test_make_comparisons_removes_the_reports_its_index_no_longer_lists(tmp_path,
                                                                         monkeypatch, capsys):
    """A run over some exemplars rewrites the index with those alone: the reports of the
    others, from an earlier run, go rather than stay unlisted and out of date. Folders
    that hold anything else stay, with what they hold."""
    from warptex.compare import REPORT_FILES

    out = tmp_path / "comparisons"
    for name in ("granite", "notes", "wood_rosewood"):
        (out / name).mkdir(parents=True)
        for report in REPORT_FILES:
            (out / name / report).write_text("earlier run")
    (out / "notes" / "plan.txt").write_text("mine")
    (out / "half").mkdir()
    (out / "half" / "sheet.png").write_text("not a report")
    _run_make_comparisons(tmp_path, monkeypatch)
    assert not (out / "granite").exists()
    assert sorted(p.name for p in (out / "notes").iterdir()) == ["plan.txt"]
    assert (out / "half" / "sheet.png").read_text() == "not a report"
    assert all((out / "wood_rosewood" / report).exists() for report in REPORT_FILES)
    assert f"removed {out / 'granite'}" in capsys.readouterr().err



def test_the_committed_comparisons_were_measured_as_the_code_measures():
    """Each table in docs/comparisons records the settings its scores were measured with;
    they are the code's own (a changed default, such as the sliced Wasserstein distance's
    directions or seed, shows here: the tables are then to be made again)."""
    from warptex.compare.report import _measure_settings

    tables = sorted((REPO / "docs" / "comparisons").glob("*/table.json"))
    assert len(tables) >= 11
    for table in tables:
        measures = json.loads(table.read_text())["run"]["measures"]
        assert measures == _measure_settings(measures["repetition_slice"]), table
