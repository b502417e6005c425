"""Finding libLLVM for Dr.Jit, and Mitsuba's LLVM variant actually rendering with it."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from warptex import llvm


@pytest.mark.parametrize(
    ("name", "major"),
    [
        ("libLLVM.so.19.1", 19),
        ("libLLVM-19.so", 19),
        ("libLLVM-17.so.1", 17),
        ("libLLVM-14.0.6.so.1", 14),
        ("libLLVM-15.so", 15),
        ("libLLVM.so.18.1.8", 18),
        ("libLLVM.so.1", None),  # Debian's llvm-18/lib/ names it so: an ABI number
        ("libLLVMSupport.so", None),
        ("libLLVM.a", None),
    ],
)
def test_major_version_from_file_name(name, major):
    assert llvm._major(name) == major


def test_find_libllvm_prefers_newest_suitable(tmp_path, monkeypatch):
    for name in ("libLLVM-15.so.1", "libLLVM-17.so.1", "libLLVM.so.19.1", "libLLVM-14.so"):
        (tmp_path / name).write_bytes(b"")
    monkeypatch.setattr(llvm, "_SEARCH_DIRS", (str(tmp_path / "missing"), str(tmp_path)))
    assert llvm.find_libllvm() == tmp_path / "libLLVM.so.19.1"


def test_find_libllvm_ignores_too_old(tmp_path, monkeypatch):
    (tmp_path / "libLLVM-15.so.1").write_bytes(b"")
    monkeypatch.setattr(llvm, "_SEARCH_DIRS", (str(tmp_path),))
    assert llvm.find_libllvm() is None


def test_find_libllvm_accepts_llvm_16_and_takes_the_newest_by_version(tmp_path, monkeypatch):
    """LLVM 16 is the oldest Dr.Jit takes; 18 is newer than 17 whatever the names' order."""
    (tmp_path / "libLLVM-16.so.1").write_bytes(b"")
    monkeypatch.setattr(llvm, "_SEARCH_DIRS", (str(tmp_path),))
    assert llvm.find_libllvm() == tmp_path / "libLLVM-16.so.1"
    assert llvm._preset_problem(str(tmp_path / "libLLVM-16.so.1")) is None
    for name in ("libLLVM-18.so.1", "libLLVM.so.17.1"):
        (tmp_path / name).write_bytes(b"")
    assert llvm.find_libllvm() == tmp_path / "libLLVM-18.so.1"


def test_find_libllvm_passes_over_what_is_no_file(tmp_path, monkeypatch):
    (tmp_path / "libLLVM-17.so.1").write_bytes(b"")
    (tmp_path / "libLLVM.so.20.1").symlink_to(tmp_path / "gone")
    (tmp_path / "libLLVM-21.so").mkdir()
    monkeypatch.setattr(llvm, "_SEARCH_DIRS", (str(tmp_path),))
    assert llvm.find_libllvm() == tmp_path / "libLLVM-17.so.1"


def test_an_empty_preset_is_searched_past(tmp_path, monkeypatch):
    (tmp_path / "libLLVM-18.so.1").write_bytes(b"")
    monkeypatch.setattr(llvm, "_SEARCH_DIRS", (str(tmp_path),))
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "")
    assert llvm.configure_drjit() == tmp_path / "libLLVM-18.so.1"


def test_a_preset_too_old_by_its_name_is_named_once(tmp_path):
    old = tmp_path / "libLLVM-15.so"
    old.write_bytes(b"")
    assert llvm._preset_problem(str(old)) == (
        f"DRJIT_LIBLLVM_PATH={old} is libLLVM 15, older than 16")


def test_run_as_a_script_it_fails_where_no_library_is_found():
    """The set-up (Makefile) installs libllvm19 where ``python warptex/llvm.py`` fails."""
    script = ("import pathlib, runpy, sys\n"
              "pathlib.Path.glob = lambda self, pattern: iter(())\n"
              "runpy.run_path(sys.argv[1], run_name='__main__')\n")
    done = subprocess.run([sys.executable, "-c", script, llvm.__file__], capture_output=True,
                          text=True, timeout=60)
    assert (done.returncode, done.stdout.strip()) == (1, "no libLLVM >= 16 found")


def test_configure_sets_env_only_when_unset(tmp_path, monkeypatch):
    (tmp_path / "libLLVM-18.so.1").write_bytes(b"")
    monkeypatch.setattr(llvm, "_SEARCH_DIRS", (str(tmp_path),))
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    assert llvm.configure_drjit() == tmp_path / "libLLVM-18.so.1"
    assert os.environ["DRJIT_LIBLLVM_PATH"] == str(tmp_path / "libLLVM-18.so.1")

    chosen = tmp_path / "custom" / "libLLVM.so"  # a user's, of no version in its name
    chosen.parent.mkdir()
    chosen.write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(chosen))
    assert llvm.configure_drjit() == chosen
    old = tmp_path / "libLLVM-15.so"
    old.write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(old))
    assert llvm.configure_drjit() is None
    # One that names no file: Dr.Jit could not start it (a traceback from Mitsuba).
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / "gone" / "libLLVM.so.19"))
    assert llvm.configure_drjit() is None
    # A bare name is Dr.Jit's dlopen's to find on the library path.
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "libLLVM-19.so")
    assert llvm.configure_drjit() == Path("libLLVM-19.so")


def test_without_home_dr_jit_caches_in_the_users_home_and_says_nothing(tmp_path, monkeypatch):
    """With HOME unset Dr.Jit printed "jit_init(): the HOME environment variable is not
    set, disabling the kernel cache" before any command's own output."""
    monkeypatch.delenv("HOME", raising=False)
    monkeypatch.delenv("DRJIT_CACHE_DIR", raising=False)
    llvm.configure_drjit()
    assert os.environ["DRJIT_CACHE_DIR"] == str(Path.home() / ".drjit")
    monkeypatch.setenv("DRJIT_CACHE_DIR", str(tmp_path))  # a user's own is kept
    llvm.configure_drjit()
    assert os.environ["DRJIT_CACHE_DIR"] == str(tmp_path)
    monkeypatch.delenv("DRJIT_CACHE_DIR")
    monkeypatch.setenv("HOME", str(tmp_path))  # and Dr.Jit's own default with a HOME
    llvm.configure_drjit()
    assert "DRJIT_CACHE_DIR" not in os.environ

    if importlib.util.find_spec("mitsuba") is None:
        return
    env = {k: v for k, v in os.environ.items() if k not in ("HOME", "DRJIT_CACHE_DIR")}
    run = subprocess.run([sys.executable, "-m", "warptex", "render", str(tmp_path / "no.xml"),
                          "-o", str(tmp_path / "out.png")],
                         capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 2
    # On a cold kernel cache the command first says that Warp builds the kernels.
    said = [line for line in run.stderr.splitlines()
            if not line.startswith("warptex: Warp is building the kernels")]
    assert said == [f"warptex: error: {tmp_path / 'no.xml'}: scene file not found"], run.stderr


def test_a_preset_link_of_no_version_is_judged_by_the_file_it_leads_to(tmp_path, monkeypatch):
    """Debian 12's libLLVM.so leads to LLVM 15, which passed for a user's choice of no
    version, then aborted the render inside LLVM."""
    old, new = tmp_path / "libLLVM-15.so.1", tmp_path / "libLLVM.so.19.1"
    for library in (old, new):
        library.write_bytes(b"")
    link = tmp_path / "lib" / "libLLVM.so"
    link.parent.mkdir()
    link.symlink_to(old)
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(link))
    assert llvm._preset_problem(str(link)) == (
        f"DRJIT_LIBLLVM_PATH={link} is libLLVM 15 ({old.resolve()}), older than 16")
    assert llvm.configure_drjit() is None
    if importlib.util.find_spec("mitsuba") is not None:
        with pytest.warns(UserWarning, match=r"falls back to scalar_rgb: .* is libLLVM 15"):
            assert llvm.best_mitsuba_variant() == "scalar_rgb"
    link.unlink()
    link.symlink_to(new)
    assert llvm.configure_drjit() == link


def test_a_preset_library_that_cannot_serve_is_named_in_the_fallback(tmp_path, monkeypatch):
    pytest.importorskip("mitsuba")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / "libfoo.so"))
    with pytest.warns(UserWarning, match=r"DRJIT_LIBLLVM_PATH=.*libfoo\.so names no file"):
        assert llvm.best_mitsuba_variant() == "scalar_rgb"


def test_a_mitsuba_without_the_llvm_variant_falls_back_and_says_so(tmp_path, monkeypatch):
    mi = pytest.importorskip("mitsuba")
    monkeypatch.setattr(llvm, "configure_drjit", lambda: tmp_path / "libLLVM-19.so")
    monkeypatch.setattr(mi, "variants", lambda: ["scalar_rgb"])
    with pytest.warns(UserWarning, match="this Mitsuba build has no llvm_ad_rgb variant"):
        assert llvm.best_mitsuba_variant() == "scalar_rgb"


@pytest.mark.parametrize(("preset", "reason"), [
    (None, r"no libLLVM >= 16 found \(install libllvm19 or set DRJIT_LIBLLVM_PATH\)$"),
    ("/nowhere/libLLVM-19.so", r"DRJIT_LIBLLVM_PATH=/nowhere/libLLVM-19\.so names no file "
                               r"\(unset it to search, or name libLLVM 16 or newer\)$"),
])
def test_falls_back_to_scalar_with_one_warning(monkeypatch, preset, reason):
    """Each reason in its words: importing warptex set DRJIT_LIBLLVM_PATH, so the search's
    own (what a machine without libLLVM says) was never the one tested."""
    pytest.importorskip("mitsuba")
    monkeypatch.setattr(llvm, "configure_drjit", lambda: None)
    if preset is None:
        monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    else:
        monkeypatch.setenv("DRJIT_LIBLLVM_PATH", preset)
    with pytest.warns(UserWarning, match=f"^warptex: Mitsuba falls back to scalar_rgb: {reason}"
                      ) as record:
        assert llvm.best_mitsuba_variant() == "scalar_rgb"
    assert len(record) == 1


_RENDER = textwrap.dedent(
    """
    import warptex  # sets DRJIT_LIBLLVM_PATH before Mitsuba starts Dr.Jit
    import mitsuba as mi
    import numpy as np

    mi.set_variant("llvm_ad_rgb")
    camera = mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0])
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "path"},
        "sensor": {
            "type": "perspective",
            "to_world": camera,
            "film": {"type": "hdrfilm", "width": 8, "height": 8},
            "sampler": {"type": "independent", "sample_count": 4},
        },
        "emitter": {"type": "constant"},
        "shape": {"type": "sphere"},
    })
    image = np.asarray(mi.render(scene))
    assert image.shape == (8, 8, 3), image.shape
    assert np.isfinite(image).all() and image.mean() > 0
    print("rendered", warptex.best_mitsuba_variant())
    """
)


def test_llvm_variant_renders_in_subprocess():
    if llvm.configure_drjit() is None:
        pytest.skip("no libLLVM >= 16 on this machine; Mitsuba uses scalar_rgb")
    # A subprocess, because an unsuitable libLLVM aborts the whole process.
    result = subprocess.run(
        [sys.executable, "-c", _RENDER], capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "rendered llvm_ad_rgb" in result.stdout


def test_a_variant_that_does_not_start_falls_back_or_is_named(monkeypatch):
    """A libLLVM that Dr.Jit cannot start: set_best_variant raised Mitsuba's ImportError,
    and --variant llvm_ad_rgb was said to need a CUDA GPU."""
    mi = pytest.importorskip("mitsuba")
    import mitsuba_plugin

    if llvm.configure_drjit() is None:
        pytest.skip("needs a libLLVM found, which Dr.Jit is made to refuse")
    real = mi.set_variant

    def refusing(name, *args):
        if name.startswith("llvm_"):
            raise ImportError("the LLVM backend is inactive")
        return real(name, *args)

    monkeypatch.setattr(mi, "set_variant", refusing)
    monkeypatch.setattr(mitsuba_plugin.warptex, "best_mitsuba_variant", lambda: "llvm_ad_rgb")
    with pytest.warns(UserWarning, match="llvm_ad_rgb does not start"):
        assert mitsuba_plugin.set_best_variant() == "scalar_rgb"
    with pytest.raises(ValueError, match=r"Mitsuba variant llvm_ad_rgb does not start here "
                                         r"\(the LLVM backend is inactive\)"):
        mitsuba_plugin.use_variant("llvm_ad_rgb")
