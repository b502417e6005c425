"""The Makefile's set-up, as `make test` and `make demo` run it on a fresh machine."""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def _make_env(**given: str) -> dict[str, str]:
    """The environment for a make of its own: `make test WARP_CACHE_PATH=...` hands its
    command line to nested makes through MAKEFLAGS, which would override what a test sets."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL", "WARP_CACHE_PATH")}
    return env | given


@pytest.mark.skipif(shutil.which("make") is None, reason="no make")
def test_a_venv_that_fails_half_way_is_made_again_by_the_next_run(tmp_path):
    """Debian's python3 without python3-venv makes the venv's folder and python, then fails
    for want of ensurepip: the next run, python3-venv installed, took that for a venv and
    failed for good on "No module named pip"."""
    shutil.copy(REPO / "Makefile", tmp_path)
    (tmp_path / "pyproject.toml").touch()
    python = tmp_path / "python3"
    python.write_text('#!/bin/sh\nmkdir -p "$3/bin" && touch "$3/bin/python" '
                      '&& chmod +x "$3/bin/python"\necho "ensurepip is not available" >&2\n'
                      "exit 1\n")
    python.chmod(0o755)
    run = subprocess.run(["make", "-s", ".venv/.installed", f"PYTHON={python}"], cwd=tmp_path,
                         env=_make_env(), capture_output=True, text=True)
    assert run.returncode != 0
    assert "ensurepip is not available" in run.stderr
    assert not (tmp_path / ".venv").exists()


@pytest.mark.skipif(shutil.which("make") is None, reason="no make")
@pytest.mark.parametrize(("given", "kept"), [(None, False), ("", False),
                                              ("/elsewhere/warp", True)])
def test_make_keeps_kernels_in_the_checkout_unless_told_otherwise(tmp_path, given, kept):
    """`export WARP_CACHE_PATH ?=` kept an empty value from the environment, which Warp
    takes for the working folder: `make test` built its kernels into the checkout's root."""
    shutil.copy(REPO / "Makefile", tmp_path)
    (tmp_path / "show.mk").write_text('show:\n\t@echo "$$WARP_CACHE_PATH"\n')
    env = _make_env() if given is None else _make_env(WARP_CACHE_PATH=given)
    run = subprocess.run(["make", "-s", "-f", "Makefile", "-f", "show.mk", "show"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, check=True)
    assert run.stdout.strip() == (given if kept else f"{tmp_path}/.cache/warp")
