"""The scripts that make the pictures in docs/: their arguments are checked before any work."""

from __future__ import annotations

import importlib.util
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
