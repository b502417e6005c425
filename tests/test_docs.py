"""The pictures in docs/: the scripts that make them check their arguments before any work,
and the README links to each."""

from __future__ import annotations

import importlib.util
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


def _run_make_comparisons(tmp_path, monkeypatch) -> list[bool]:
    """``docs/make_comparisons.py`` over the rosewood photo alone, writing under
    ``tmp_path``, with a ``compare`` of meaningless scores in no time and no reports
    written; the progress flags it passed to ``compare``."""
    from warptex.compare import Comparison, MethodResult

    make_comparisons = _script("make_comparisons")
    photos = tmp_path / "photos"
    photos.mkdir()
    shutil.copy(REPO / "scenes" / "textures" / "wood_rosewood_64.png", photos)
    bars = []

    def compare(setup, methods, progress=True):
        bars.append(progress)
        return Comparison(setup, [MethodResult(m, [0.1] * 3, [0.2] * 3, [0.0] * 3, [0.0] * 3,
                                               0.5, 1.0, 0.0, precompute_seconds=2.0)
                                  for m in methods])

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
